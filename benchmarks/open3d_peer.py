"""The peer of the fusion benchmark: the same profile stream integrated by Open3D's
``VoxelBlockGrid`` (the TSDF a user would otherwise pick), with the same voxel (0.5 mm), the
same truncation (+-3 voxels), 8**3 blocks like ours and the same number of threads.

A laser line is a pinhole camera that sees one plane: each profile becomes a depth image of the
sensor's columns (``u = fx x / z + cx`` with the sensor's fan: 640 columns over +-0.26 rad),
depth ``z_S`` [mm] (``depth_scale = 1``). Open3D's projective update reads a voxel's depth
only where its projection lies inside the image (``0 <= v <= rows - 1``), so a one-row image
updates nothing but voxels exactly on the laser plane, and its block allocation
(``compute_unique_block_coordinates``) samples every fourth row and column, so an image of
fewer than four rows allocates nothing. The image therefore has four identical rows with
``cy = 1.5`` and ``fy`` chosen so the rows cover the voxels whose centre is within half a voxel
of the plane at the sensor's stand-off (``fy = 3 standoff / voxel``), the slab our ray walk
updates. Blocks are allocated per profile from the same depth image, Open3D's documented
integration path.

Open3D's grid is shifted by a quarter voxel on each axis (its vertices shifted back). Open3D
samples its field at ``i * voxel``; unshifted, a plane at a multiple of the voxel (the static
scene's plate at z = 0, its box faces at 40 and 80 mm) runs through its sample points, where
the interpolated vertices land on the plane whatever the noise: 52 % of its plate vertices had
zero error and its RMS read 0.035 mm against 0.052-0.064 mm at other offsets. A half voxel
(ours: voxel centres at ``(i + 1/2) * voxel``) puts the growing stream's laser planes at whole
millimetres exactly on the edge of the one-voxel slab below, which then missed most voxels
(30,031 vertices against 256,798). A quarter voxel is degenerate for neither (194,566 vertices;
static RMS 0.063 mm).

Poses are the ones our synchroniser interpolates (computed before the clock starts, so Open3D
is timed on integration alone, ours end to end including sync and registration).

The number of threads must be fixed before Open3D is imported (``OMP_NUM_THREADS``): import
this module first.
"""

from __future__ import annotations

import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "2")

import numpy as np  # noqa: E402

from dm2.core.frames import invert  # noqa: E402
from dm2.core.messages import Profile  # noqa: E402
from dm2.fusion.sync import StreamSync, SyncedProfile  # noqa: E402

FAN_HALF_RAD = 0.26   # the synthetic sensor's fan (tests/test_monitor_scene.py: scan_profile)
COLUMNS = 640
ROWS = 4  # the fewest rows Open3D's block allocation samples (every fourth row)
STANDOFF_MM = 95.0    # sensor to spot (make_calibration)


def synced_profiles(cal, msgs, max_pose_gap_s: float, reorder_window_s: float):
    """``[(xz_S (n, 2), T_O_S (4, 4))]`` of every usable profile, in stream order."""
    sync = StreamSync(cal.T_B_S.keys(), max_pose_gap_s, reorder_window_s)
    out = []

    def take(items):
        for it in items:
            if type(it) is SyncedProfile:
                T_O_S = invert(it.T_B_F @ cal.T_F_O) @ cal.T_B_S[it.profile.sensor_id]
                out.append((it.xz_S, T_O_S))

    for m in msgs:
        take(sync.push(m))
    take(sync.flush())
    return out


class Open3DFusion:
    """Open3D ``VoxelBlockGrid`` fed one depth image per profile."""

    def __init__(self, voxel_mm: float, truncation_voxels: float, block_count: int = 60000):
        import open3d as o3d
        import open3d.core as o3c

        self.o3d, self.o3c = o3d, o3c
        self.voxel_mm = float(voxel_mm)
        self.T_grid_O = np.eye(4)  # Open3D's frame: O shifted by a quarter voxel (module doc)
        self.T_grid_O[:3, 3] = 0.25 * self.voxel_mm
        self.trunc = float(truncation_voxels)
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
            attr_channels=((1,), (1,)), voxel_size=self.voxel_mm, block_resolution=8,
            block_count=block_count, device=o3c.Device("CPU:0"))
        fx = (COLUMNS - 1) / (2.0 * np.tan(FAN_HALF_RAD))
        fy = (ROWS - 1) * STANDOFF_MM / self.voxel_mm
        self.fx, self.cx = fx, (COLUMNS - 1) / 2.0
        K = np.array([[fx, 0, self.cx], [0, fy, (ROWS - 1) / 2.0], [0, 0, 1]])
        self.intrinsic = o3c.Tensor(K, o3c.float64)
        self._depth = np.zeros((ROWS, COLUMNS), np.float32)
        self.points = 0

    def depth_image(self, xz_S: np.ndarray) -> np.ndarray:
        """(ROWS, COLUMNS) float32 depth [mm] of one profile (0 where the column has no point)
        and the number of points in it."""
        d = self._depth
        d[:] = 0.0
        z = xz_S[:, 1]
        u = np.rint(self.fx * xz_S[:, 0] / z + self.cx).astype(np.int64)
        ok = (u >= 0) & (u < COLUMNS) & (z > 0)
        d[0, u[ok]] = z[ok]
        d[1:] = d[0]
        return d, int(np.count_nonzero(ok))

    def integrate(self, profiles) -> None:
        o3d, o3c = self.o3d, self.o3c
        depth_max = 4.0 * STANDOFF_MM
        for xz_S, T_O_S in profiles:
            image, n = self.depth_image(xz_S)
            if n == 0:  # Open3D refuses an image that touches no block
                continue
            depth = o3d.t.geometry.Image(o3c.Tensor(image))
            extrinsic = o3c.Tensor(invert(self.T_grid_O @ T_O_S), o3c.float64)
            blocks = self.vbg.compute_unique_block_coordinates(
                depth, self.intrinsic, extrinsic, 1.0, depth_max, self.trunc)
            self.vbg.integrate(blocks, depth, self.intrinsic, extrinsic, 1.0, depth_max,
                               self.trunc)
            self.points += n

    def extract(self, min_weight: float):
        """``(vertices (n, 3), faces (m, 3))`` of the zero level set [mm] over voxels of weight
        ``>= min_weight``, as ours meshes. Open3D keeps a voxel only when its weight is strictly
        above ``weight_threshold`` (at 1.0 it dropped every voxel seen by exactly one profile:
        12,872 vertices against 256,798 on the benchmark's stream), so the threshold passed is
        the float32 just below ``min_weight``."""
        below = float(np.nextafter(np.float32(min_weight), np.float32(0.0)))
        mesh = self.vbg.extract_triangle_mesh(weight_threshold=below)
        vertices_O = mesh.vertex.positions.numpy() - self.T_grid_O[:3, 3].astype(np.float32)
        return vertices_O, mesh.triangle.indices.numpy()


def open3d_run(profiles, voxel_mm: float, truncation_voxels: float):
    """(Open3DFusion, seconds) of one integration of ``profiles``."""
    fusion = Open3DFusion(voxel_mm, truncation_voxels)
    t0 = time.perf_counter()
    fusion.integrate(profiles)
    return fusion, time.perf_counter() - t0


def surface_error(vertices_O: np.ndarray, sdf) -> tuple[float, float, int]:
    """RMS and p95 [mm] of ``|sdf(v)|`` over the vertices, and their number."""
    d = np.abs(sdf(np.asarray(vertices_O, np.float64)))
    if d.size == 0:
        return float("nan"), float("nan"), 0
    return float(np.sqrt(np.mean(d ** 2))), float(np.percentile(d, 95)), int(d.size)


def count_points(msgs) -> int:
    return sum(int(np.count_nonzero(m.valid)) for m in msgs if isinstance(m, Profile))
