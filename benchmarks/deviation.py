"""Benchmark: layer deviation + segmentation + tracking on a 200 k vertex layer (goal <= 1 s),
real-time deviation latency per frame set (goal <= 5 ms p99), and the near-net reference's
add_states per batch of 25 robot states (what a session integrates per frame set).

Run: .venv/bin/python benchmarks/deviation.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import time
from types import SimpleNamespace

import numpy as np

from dm2.core.config import MonitorConfig
from dm2.defects.layer_analysis import LayerAnalysis
from dm2.defects.realtime import RealtimeDeviation
from dm2.fusion.tsdf.field import SparseTSDF
from dm2.reference.height_map import ReferenceMap

CELL = 0.25


def reference_pad(height=4.0, side=100.0) -> ReferenceMap:
    n = int(120 / CELL)
    c = (np.arange(n) + 0.5) * CELL
    xx, yy = np.meshgrid(c, c)
    h = np.where((np.abs(xx - 60) <= side / 2) & (np.abs(yy - 60) <= side / 2), height, 0.0)
    return ReferenceMap(h, CELL, layer=4)


def measured_layer(ref: ReferenceMap, n_side: int, rng) -> SimpleNamespace:
    """A ``n_side**2`` vertex grid over the pad top with noise, two bumps and a dent."""
    x = np.linspace(12.0, 108.0, n_side)
    xx, yy = np.meshgrid(x, x)
    xy = np.column_stack([xx.ravel(), yy.ravel()])
    z = ref.height_at(xy) + rng.normal(0, 0.03, len(xy))
    for cx, cy, a in ((40, 40, 1.0), (80, 70, 0.7), (60, 90, -0.9)):
        z += a * np.exp(-((xy[:, 0] - cx) ** 2 + (xy[:, 1] - cy) ** 2) / (2 * 2.5 ** 2))
    idx = np.arange(n_side * n_side).reshape(n_side, n_side)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    return SimpleNamespace(vertices_O=np.column_stack([xy, z]), faces=faces,
                           weight=np.full(len(xy), 5.0), normals_O=None)


def bench_layer(repeats: int) -> None:
    rng = np.random.default_rng(0)
    cfg = MonitorConfig()
    ref = reference_pad()
    surf = measured_layer(ref, 448, rng)
    mon = LayerAnalysis(cfg)
    mon.analyse_layer(surf, ref, layer=0)  # warm-up (numba, Open3D)
    totals, stages = [], []
    for k in range(repeats):
        t0 = time.perf_counter()
        res = mon.analyse_layer(surf, ref, layer=k + 1)
        totals.append(time.perf_counter() - t0)
        stages.append(res.timing_s)
    med = {s: float(np.median([t[s] for t in stages])) for s in stages[0]}
    print(f"layer analysis, {len(surf.vertices_O)} vertices, {len(res.regions)} regions: "
          f"median {np.median(totals) * 1e3:.0f} ms over {repeats} runs (goal <= 1000 ms); "
          + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in med.items()))


def bench_realtime(frames: int) -> None:
    cfg = MonitorConfig()
    ref = reference_pad()
    tsdf = SparseTSDF(cfg.voxel_mm, cfg.truncation_voxels * cfg.voxel_mm, cfg.weight_cap)
    rt = RealtimeDeviation(cfg)
    lat = []
    for k in range(frames + 5):
        t = k / 10.0
        spot = np.array([20.0 + (3.0 * k) % 80.0, 20.0 + 2.0 * (k // 27), 4.0])
        pts, origins = [], []
        for az in np.radians([90.0, 210.0, 330.0]):
            u = np.array([np.cos(az), np.sin(az)])
            s = np.linspace(-21.0, 21.0, 640)
            xy = spot[:2] + s[:, None] * np.array([-u[1], u[0]])
            pts.append(np.column_stack([xy, ref.height_at(xy)]))
            origins.append(np.tile([*(spot[:2] + 54.5 * u), spot[2] + 77.8], (640, 1)))
        tsdf.integrate(np.vstack(origins), np.vstack(pts), np.ones(3 * 640, bool))
        t0 = time.perf_counter()
        rt.update_from_tsdf(tsdf, spot, t, ref)
        if k >= 5:  # the first frames compile the kernels
            lat.append(time.perf_counter() - t0)
    lat = np.array(lat) * 1e3
    print(f"real-time deviation per frame set ({frames} frame sets of 3 x 640 points): "
          f"p50 {np.percentile(lat, 50):.2f} ms, p99 {np.percentile(lat, 99):.2f} ms "
          "(goal p99 <= 5 ms)")


def raster_poses(rate_hz=250.0, speed=30.0, spacing=2.0, side=40.0, layers=2, tilt_deg=0.0):
    """(stamps (m,), flange poses (m, 4, 4)) of a raster over a square at 250 Hz, with the
    plate on the flange (``T_F_O`` identity) and the nozzle at the origin of B spraying down."""
    from scipy.spatial.transform import Rotation

    from dm2.core.frames import make_T

    pts = []
    for layer in range(layers):
        for k, y in enumerate(np.arange(60 - side / 2, 60 + side / 2 + 1e-9, spacing)):
            x = np.arange(0.0, side + 1e-9, speed / rate_hz) + 60 - side / 2
            xs = x if k % 2 == 0 else x[::-1]
            pts.append(np.column_stack([xs, np.full_like(xs, y), np.full_like(xs, 0.8 * layer)]))
    pts = np.vstack(pts)
    R = Rotation.from_euler("x", 180.0 + tilt_deg, degrees=True)  # R_B_O: z_O -> -z_B
    T = np.array([make_T(R, np.array([0.0, 0.0, 30.0]) - R.apply(p)) for p in pts])
    return np.arange(len(pts)) / rate_hz, T


def bench_reference(repeats: int) -> None:
    from dm2.core.config import ProcessConfig
    from dm2.core.frames import make_T
    from dm2.core.messages import Calibration
    from dm2.reference.model import NearNetReference

    cal = Calibration({}, np.eye(4), make_T(np.eye(3), [0.0, 0.0, 0.0]))
    stamps, T = raster_poses()
    per_call = []
    for _ in range(repeats):
        ref = NearNetReference(ProcessConfig(feed_g_min=26.0), MonitorConfig(), cal)
        ref.add_states(stamps[:25], T[:25])  # warm-up (numba cache)
        t0 = time.perf_counter()
        calls = 0
        for a in range(25, len(stamps), 25):
            ref.add_states(stamps[a:a + 25], T[a:a + 25])
            calls += 1
        per_call.append((time.perf_counter() - t0) / calls)
    print(f"reference add_states per 25 states (250 Hz raster, 2 layers, {calls} calls, "
          f"{ref.snapshot().heights_mm.shape} map): median {np.median(per_call) * 1e3:.3f} ms "
          f"over {repeats} runs")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    bench_layer(args.repeats)
    bench_realtime(args.frames)
    bench_reference(args.repeats)


if __name__ == "__main__":
    main()
