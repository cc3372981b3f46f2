"""The reconstruction check's distance to the twin's true surface: in place on the truth's
grid (``dm2.bench.reconstruction.grid_mesh_distance``) against Open3D's
``RaycastingScene.compute_distance`` (BVH build included: every layer has its own truth).

The truth is a twisted tower as the twin's height field holds it (0.25 mm cells, 60 layers of
1 mm, each a 40 mm square turned 0.75 degrees further, on a 120 mm plate, cropped to the part
plus 10 mm as the twin writes ``truth/layer_NNN.ply``); the query points are every other true
vertex moved by N(0, 0.1 mm) (a reconstruction), plus 1 % uniform in the part's box (stray
vertices up to the part's height away). Printed: the median wall time of ``--runs`` runs of
each, the ratio, the points per second and the largest difference of the two distances.

    .venv/bin/python benchmarks/reconstruction_check.py [--runs 5] [--layers 60]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]

from dm2.bench.reconstruction import grid_mesh_distance, grid_of_mesh  # noqa: E402
from twin.world.heightfield import HeightField  # noqa: E402


def tower_field(layers: int) -> HeightField:
    hf = HeightField(size_mm=(120.0, 120.0), cell_mm=0.25, thickness_mm=10.0)
    x, y = hf.centres_mm()
    gx, gy = np.meshgrid(x - 60.0, y - 60.0)
    h = np.zeros_like(gx)
    for k in range(layers):
        a = np.deg2rad(0.75 * k)
        u = np.cos(a) * gx + np.sin(a) * gy
        v = -np.sin(a) * gx + np.cos(a) * gy
        inside = (np.abs(u) < 20.0) & (np.abs(v) < 20.0) & (h >= k - 1e-9)
        h[inside] = k + 1.0
    hf._h[:] = h
    return hf


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--layers", type=int, default=60)
    args = ap.parse_args()
    import open3d as o3d

    hf = tower_field(args.layers)
    mesh = hf.to_mesh(window_mm=(30.0, 30.0, 90.0, 90.0))
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    rng = np.random.default_rng(0)
    near = v[::2] + rng.normal(0.0, 0.1, v[::2].shape)
    stray = rng.uniform([32, 32, 0], [88, 88, args.layers], (len(near) // 100, 3))
    points = np.concatenate([near, stray])
    print(f"truth: {len(v)} vertices, {len(f)} triangles; {len(points)} query points "
          f"({len(stray)} stray)")

    def ours():
        grid = grid_of_mesh(v, f)  # (the check finds the grid in every truth it reads)
        return grid_mesh_distance(points, *grid)

    def open3d():
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                            o3d.core.Tensor(f.astype(np.uint32)))
        return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()

    d_ours, d_o3d = ours(), open3d()  # (compiles / warms up)
    times = {}
    for name, fn in (("grid, in place", ours), ("Open3D RaycastingScene", open3d)):
        runs = []
        for _ in range(args.runs):
            t0 = time.perf_counter()
            fn()
            runs.append(time.perf_counter() - t0)
        times[name] = statistics.median(runs)
        print(f"{name:>24}: {times[name] * 1e3:8.1f} ms  "
              f"({len(points) / times[name] / 1e6:.2f} M points/s, median of {args.runs})")
    print(f"ratio: {times['Open3D RaycastingScene'] / times['grid, in place']:.1f}x faster "
          f"than Open3D; largest difference {np.abs(d_ours - d_o3d).max():.2e} mm "
          f"(Open3D works in float32)")


if __name__ == "__main__":
    main()
