"""Virtual profiler throughput: three 640-ray profiles per trigger on a part-bearing height field.

Prints laser rays per second and profiles per second (median of 5 runs) for the full scan
(laser ray cast, camera line-of-sight cast, nozzle occluder, noise), and the speed-up over the
alternative the height field avoids: rebuilding an Open3D BVH of the surface every time the
deposit changes and casting only the laser rays on it.

    .venv/bin/python benchmarks/profiler.py [--triggers 100] [--runs 5]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

# Import the packages from the repository root, never sibling scripts of the same name.
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

import numpy as np  # noqa: E402

from dm2.core.config import PartConfig, SensorConfig  # noqa: E402
from dm2.core.messages import SENSOR_IDS  # noqa: E402
from scenarios.parts import build_part  # noqa: E402
from twin.cell.cell import CellModel  # noqa: E402
from twin.profiler.occluders import nozzle_occluder  # noqa: E402
from twin.profiler.sensor import VirtualProfiler  # noqa: E402
from twin.schema import CellConfig, NoiseConfig  # noqa: E402
from twin.world import heightfield  # noqa: E402
from twin.world.heightfield import HeightField  # noqa: E402


def _setup():
    cell_cfg = CellConfig()
    cell = CellModel.from_config(cell_cfg, standoff_mm=30.0)
    size = cell_cfg.plate_size_mm
    mesh = build_part(PartConfig(generator="seven_sided"), size)
    hf = HeightField.from_mesh(mesh, size[:2], 0.25, size[2])
    sensors, noise = SensorConfig(), NoiseConfig(speckle_sigma_mm=0.02, dropout_prob=0.01,
                                                 outlier_prob=0.001)
    profilers = [VirtualProfiler(sid, _camera_outboard(cell.T_B_S[sid], cell.spot_B), sensors,
                                 noise, seed=1) for sid in SENSOR_IDS]
    occluders = [nozzle_occluder(cell.T_B_N, cell_cfg)]
    return cell, hf, profilers, occluders


def _camera_outboard(T_B_S, spot_B):
    """The profiler turned half a turn about its viewing axis if its camera (+y_S) would sit
    nearer the nozzle axis than the laser: mounted that way the nozzle hides the spot."""
    radial = T_B_S[:2, 3] - spot_B[:2]
    if T_B_S[:2, 1] @ radial < 0.0:
        return T_B_S @ np.diag([-1.0, -1.0, 1.0, 1.0])
    return T_B_S


def _poses(cell, hf, n):
    """Plate poses sweeping the spot across the part's top, level spray."""
    lx, ly = hf.size_mm
    s = np.linspace(0.0, 1.0, n)
    xy = np.column_stack([lx * (0.3 + 0.4 * s), ly * (0.45 + 0.1 * np.sin(6 * s))])
    z = hf.height_at(xy)
    pos = np.column_stack([xy, z])
    axis = np.tile([0.0, 0.0, -1.0], (n, 1))
    return cell.T_B_O_for(pos, axis)


def run_profiler(hf, profilers, occluders, poses) -> tuple[float, float]:
    """Seconds for all scans and the fraction of valid points."""
    t0 = time.perf_counter()
    valid = 0
    for k, T_B_O in enumerate(poses):
        for prof in profilers:
            valid += int(prof.scan(hf, T_B_O, 0.1 * k, k, occluders).valid.sum())
    elapsed = time.perf_counter() - t0
    return elapsed, valid / (len(poses) * len(profilers) * profilers[0].dirs_S.shape[0])


def run_bvh_baseline(hf, profilers, poses) -> float:
    """Seconds to rebuild an Open3D scene per trigger and cast the three laser fans on it."""
    import open3d as o3d

    mesh = hf.to_mesh(closed=True)
    verts = o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32))
    faces = o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32))
    t0 = time.perf_counter()
    for T_B_O in poses:
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(verts, faces)
        rays = []
        for prof in profilers:
            T_O_S = np.linalg.inv(T_B_O) @ prof.T_B_S
            d = prof.dirs_S @ T_O_S[:3, :3].T
            rays.append(np.hstack([np.broadcast_to(T_O_S[:3, 3], d.shape), d]))
        scene.cast_rays(o3d.core.Tensor(np.vstack(rays).astype(np.float32)))
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triggers", type=int, default=100)
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()

    cell, hf, profilers, occluders = _setup()
    poses = _poses(cell, hf, args.triggers)
    run_profiler(hf, profilers, occluders, poses[:2])  # compile / warm caches
    times, frac = [], 0.0
    for _ in range(args.runs):
        dt, frac = run_profiler(hf, profilers, occluders, poses)
        times.append(dt)
    med = statistics.median(times)
    n_prof = args.triggers * len(profilers)
    n_rays = n_prof * profilers[0].dirs_S.shape[0]
    serial = []
    saved = heightfield._PARALLEL_MIN_RAYS
    heightfield._PARALLEL_MIN_RAYS = 1 << 62  # the same scans with single-threaded ray casts
    try:
        for _ in range(args.runs):
            serial.append(run_profiler(hf, profilers, occluders, poses)[0])
    finally:
        heightfield._PARALLEL_MIN_RAYS = saved
    med_serial = statistics.median(serial)
    base_poses = poses[: max(2, args.triggers // 10)]
    base = statistics.median(run_bvh_baseline(hf, profilers, base_poses)
                             for _ in range(args.runs))
    base_per_trigger = base / len(base_poses)
    ours_per_trigger = med / args.triggers
    print(f"height field {hf.shape[1]} x {hf.shape[0]} cells at {hf.cell_mm} mm, "
          f"part top {hf.heights_mm.max():.1f} mm; {args.triggers} triggers x 3 profiles x "
          f"{profilers[0].dirs_S.shape[0]} rays, median of {args.runs} runs")
    print(f"valid points: {100 * frac:.1f} %")
    print(f"laser rays per second (full scan incl. camera sight lines, occluder, noise): "
          f"{n_rays / med:,.0f}")
    print(f"profiles per second: {n_prof / med:,.0f}  "
          f"({1e3 * ours_per_trigger:.2f} ms per 3-profile trigger)")
    print(f"  with single-threaded HeightField ray casts: {n_rays / med_serial:,.0f} rays/s, "
          f"{n_prof / med_serial:,.0f} profiles/s")
    print(f"BVH rebuild baseline: {1e3 * base_per_trigger:.1f} ms per trigger; "
          f"height field is {base_per_trigger / ours_per_trigger:.1f}x faster")


if __name__ == "__main__":
    main()
