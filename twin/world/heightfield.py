"""The twin's world surface: a height field over the substrate plate, in the work object frame O.

``heights_mm[j, i]`` is the top surface ``z_O`` [mm] at the cell centre
``((i + 0.5) * cell_mm, (j + 0.5) * cell_mm)``; 0 is the bare plate top. Between centres the
surface is the bilinear interpolation of the four neighbouring centres; in the outer half cell
along the plate border it is extended flat. The solid is everything on the plate footprint
``[0, Lx] x [0, Ly]`` between the plate bottom ``z = -thickness_mm`` and that surface, so rays
hit the top surface, the plate's side faces and its bottom; rays outside the footprint miss.

Limits of a height field: one height per (x, y), so no undercuts, overhanging lips or closed
cavities are represented (an overhang deposited outward appears as the top of its silhouette).
The laser profilers look down at the part from 55 degrees and cannot see undercuts either.

The height array is exposed read-only; change it through :attr:`HeightField.heights_mm`
assignment (whole array), :meth:`add_heights` or the deposition kernels, which keep the
ray-casting acceleration bounds valid.
"""

from __future__ import annotations

import logging

import numpy as np

from dm2.core.tolerances import ROUNDING_SLACK
from twin.world import heightfield_kernels as K

log = logging.getLogger(__name__)

HEIGHTFIELD_CELL_MM = 0.25  # the twin's deposit grid: a quarter of the TSDF's 0.5 mm voxel
_PARALLEL_MIN_RAYS = 16384  # thread start-up costs more than a 640-ray fan gains


class HeightField:
    """Top surface of plate plus part on a regular grid in O.

    Parameters
    ----------
    size_mm : (2,) float, plate extent ``(Lx, Ly)`` [mm]
    cell_mm : float, grid spacing [mm]
    thickness_mm : float, plate thickness below ``z = 0`` [mm]
    """

    def __init__(self, size_mm=(120.0, 120.0), cell_mm: float = 0.25, thickness_mm: float = 6.0):
        size = np.asarray(size_mm, dtype=np.float64).reshape(-1)
        if size.shape[0] < 2 or not np.all(np.isfinite(size[:2])) or np.any(size[:2] <= 0):
            raise ValueError(f"HeightField.size_mm: need two positive extents, got {size_mm!r}")
        if not (np.isfinite(cell_mm) and cell_mm > 0):
            raise ValueError(f"HeightField.cell_mm: must be positive, got {cell_mm!r}")
        if not (np.isfinite(thickness_mm) and thickness_mm > 0):
            raise ValueError(f"HeightField.thickness_mm: must be positive, got {thickness_mm!r}")
        nx = int(round(size[0] / cell_mm))
        ny = int(round(size[1] / cell_mm))
        if not (np.isclose(nx * cell_mm, size[0], rtol=ROUNDING_SLACK, atol=0)
                and np.isclose(ny * cell_mm, size[1], rtol=ROUNDING_SLACK, atol=0)):
            raise ValueError(f"HeightField: size_mm {tuple(size[:2])} is not a multiple of "
                             f"cell_mm {cell_mm}")
        self.size_mm = (float(size[0]), float(size[1]))
        self.cell_mm = float(cell_mm)
        self.thickness_mm = float(thickness_mm)
        self._h = np.zeros((ny, nx), dtype=np.float64)
        self._bmax = np.zeros((ny // K.BLOCK + 1, nx // K.BLOCK + 1), dtype=np.float64)
        self._zmax = np.zeros(1, dtype=np.float64)
        # cells changed since the last take_changes: [j_min, j_max, i_min, i_max] (inclusive)
        self._dirty = np.zeros(4, dtype=np.int64)
        self._refresh()

    # --- state -----------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """``(ny, nx)`` cells."""
        return self._h.shape

    @property
    def heights_mm(self) -> np.ndarray:
        """(ny, nx) float64 [mm], read-only view of the top surface at cell centres."""
        view = self._h.view()
        view.setflags(write=False)
        return view

    @heights_mm.setter
    def heights_mm(self, value) -> None:
        arr = np.asarray(value, dtype=np.float64)
        if arr.shape != self._h.shape:
            raise ValueError(f"HeightField.heights_mm: expected shape {self._h.shape}, "
                             f"got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError("HeightField.heights_mm: contains NaN or infinite values")
        self._h[...] = np.maximum(arr, -self.thickness_mm)
        self._refresh()

    def add_heights(self, delta_mm: np.ndarray) -> None:
        """Add a (ny, nx) height change [mm] (the surface never sinks below the plate bottom)."""
        delta = np.asarray(delta_mm, dtype=np.float64)
        self.heights_mm = self._h + delta

    def _refresh(self) -> None:
        K.compute_block_max(self._h, self._bmax)
        self._zmax[0] = max(float(self._h.max()), 0.0)
        ny, nx = self._h.shape
        self._dirty[:] = (0, ny - 1, 0, nx - 1)

    def copy_changes_to(self, mirror: HeightField) -> None:
        """Make ``mirror`` (made by :meth:`copy`) equal to this field again, bit for bit.

        Only the cells changed since the previous call (and their acceleration blocks) are
        copied, so keeping a mirror for a reader on another thread costs little; a field keeps
        track of changes for one mirror (this or :meth:`take_changes`).
        """
        if mirror._h.shape != self._h.shape:
            raise ValueError(f"HeightField.copy_changes_to: mirror shape {mirror._h.shape} "
                             f"differs from {self._h.shape}")
        mirror.apply_changes(self.take_changes())

    def take_changes(self) -> tuple:
        """The cells changed since the previous take (or :meth:`copy_changes_to`), copied, for
        :meth:`apply_changes` on a mirror, possibly later or on another thread:
        ``(j0, i0, heights (h, w), bj0, bi0, bounds (bh, bw), zmax)``, heights None when no
        cell changed."""
        j0, j1, i0, i1 = self._dirty.tolist()
        ny, nx = self._h.shape
        self._dirty[:] = (ny, -1, nx, -1)  # empty
        zmax = float(self._zmax[0])
        if j0 > j1 or i0 > i1:
            return (0, 0, None, 0, 0, None, zmax)
        b = K.BLOCK  # node (k, m) bounds the blocks of patches k..k+1, m..m+1
        bj0, bj1, bi0, bi1 = j0 // b, (j1 + 1) // b + 1, i0 // b, (i1 + 1) // b + 1
        return (j0, i0, self._h[j0:j1 + 1, i0:i1 + 1].copy(), bj0, bi0,
                self._bmax[bj0:bj1, bi0:bi1].copy(), zmax)

    def apply_changes(self, changes: tuple) -> None:
        """Apply :meth:`take_changes` of the field this one mirrors (same shape)."""
        j0, i0, heights, bj0, bi0, bounds, zmax = changes
        if heights is not None:
            self._h[j0:j0 + heights.shape[0], i0:i0 + heights.shape[1]] = heights
            self._bmax[bj0:bj0 + bounds.shape[0], bi0:bi0 + bounds.shape[1]] = bounds
        self._zmax[0] = zmax

    def centres_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates ``x (nx,)``, ``y (ny,)`` [mm] in O."""
        ny, nx = self._h.shape
        return (np.arange(nx) + 0.5) * self.cell_mm, (np.arange(ny) + 0.5) * self.cell_mm

    def copy(self) -> HeightField:
        """An independent deep copy."""
        out = HeightField.__new__(HeightField)
        out.size_mm = self.size_mm
        out.cell_mm = self.cell_mm
        out.thickness_mm = self.thickness_mm
        out._h = self._h.copy()
        out._bmax = self._bmax.copy()
        out._zmax = self._zmax.copy()
        out._dirty = self._dirty.copy()
        return out

    # --- queries ---------------------------------------------------------------------------
    def raycast(self, origins_O, dirs_O, max_range_mm: float = np.inf) -> np.ndarray:
        """Distance along each ray to the first hit of the solid.

        Parameters
        ----------
        origins_O : (n, 3) float64 [mm]
        dirs_O : (n, 3) float64, unit directions
        max_range_mm : float, rays that would hit farther report a miss

        Returns
        -------
        t_mm : (n,) float64 [mm], ``np.inf`` on a miss; hit point = origin + t * dir
        """
        o = np.ascontiguousarray(origins_O, dtype=np.float64)
        d = np.ascontiguousarray(dirs_O, dtype=np.float64)
        if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
            raise ValueError(f"HeightField.raycast: origins_O and dirs_O must both be (n, 3), "
                             f"got {o.shape} and {d.shape}")
        out = np.empty(o.shape[0], dtype=np.float64)
        kernel = K.raycast_parallel if o.shape[0] >= _PARALLEL_MIN_RAYS else K.raycast_serial
        kernel(self._h, self._bmax, self.cell_mm, self.thickness_mm, self._zmax[0], o, d,
               float(max_range_mm), out)
        return out

    def height_at(self, xy_O) -> np.ndarray:
        """Bilinear surface height (n,) [mm] at ``xy_O (n, 2)`` [mm]; NaN off the plate."""
        xy = self._xy(xy_O, "height_at")
        out = np.empty(xy.shape[0], dtype=np.float64)
        K.heights_at(self._h, self.cell_mm, xy, out)
        return out

    def normals_at(self, xy_O) -> np.ndarray:
        """Unit upward surface normals (n, 3) at ``xy_O (n, 2)`` [mm] (clamped to the plate)."""
        xy = self._xy(xy_O, "normals_at")
        out = np.empty((xy.shape[0], 3), dtype=np.float64)
        K.normals_at(self._h, self.cell_mm, xy, out)
        return out

    @staticmethod
    def _xy(xy_O, name: str) -> np.ndarray:
        xy = np.ascontiguousarray(xy_O, dtype=np.float64)
        if xy.ndim == 1 and xy.shape[0] == 2:
            xy = xy[None, :]
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"HeightField.{name}: expected xy_O of shape (n, 2), got {xy.shape}")
        return xy

    # --- conversion ------------------------------------------------------------------------
    @classmethod
    def from_mesh(cls, mesh_O, size_mm=(120.0, 120.0), cell_mm: float = 0.25,
                  thickness_mm: float = 6.0) -> HeightField:
        """Rasterise a watertight part mesh (in O, base at ``z = 0``) by top-down ray casting.

        Each cell centre takes the highest surface point of the mesh above it (0 where the part
        does not cover it); undercuts are lost, as in any height field.
        """
        import open3d as o3d

        hf = cls(size_mm, cell_mm, thickness_mm)
        x, y = hf.centres_mm()
        gx, gy = np.meshgrid(x, y)
        verts = np.asarray(mesh_O.vertices, dtype=np.float32)
        faces = np.asarray(mesh_O.faces, dtype=np.uint32)
        if verts.size == 0 or faces.size == 0:
            raise ValueError("HeightField.from_mesh: the mesh is empty")
        top = float(verts[:, 2].max()) + 10.0
        rays = np.zeros((gx.size, 6), dtype=np.float32)
        rays[:, 0] = gx.ravel()
        rays[:, 1] = gy.ravel()
        rays[:, 2] = top
        rays[:, 5] = -1.0
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(faces))
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        z = np.where(np.isfinite(t), top - t, 0.0).reshape(gx.shape)
        hf.heights_mm = np.maximum(z, 0.0)
        log.debug("rasterised mesh of %d faces onto %s cells", len(faces), hf.shape)
        return hf

    def to_mesh(self, closed: bool = False, window_mm=None):
        """The surface as a ``trimesh.Trimesh`` in O [mm].

        Vertices are the cell centres plus the plate border (flat extension), two triangles per
        quad; the bilinear patches are split along one diagonal. ``closed=True`` adds the plate's
        side faces and bottom for a watertight solid. ``window_mm = (xmin, ymin, xmax, ymax)``
        keeps only the cell centres inside that rectangle (no border, no closing).
        """
        import trimesh

        x, y = self.centres_mm()
        if window_mm is not None:
            x0, y0, x1, y1 = (float(v) for v in window_mm)
            ci = np.flatnonzero((x >= x0) & (x <= x1))
            cj = np.flatnonzero((y >= y0) & (y <= y1))
            if len(ci) < 2 or len(cj) < 2:
                raise ValueError(f"HeightField.to_mesh: window {window_mm} holds fewer than "
                                 f"2 x 2 cell centres")
            xs, ys = x[ci], y[cj]
            zp = self._h[cj[0]:cj[-1] + 1, ci[0]:ci[-1] + 1]
            closed = False
        else:
            xs = np.concatenate([[0.0], x, [self.size_mm[0]]])
            ys = np.concatenate([[0.0], y, [self.size_mm[1]]])
            zp = np.pad(self._h, 1, mode="edge")
        gx, gy = np.meshgrid(xs, ys)
        verts = np.column_stack([gx.ravel(), gy.ravel(), zp.ravel()])
        H, W = zp.shape
        jj, ii = np.meshgrid(np.arange(H - 1), np.arange(W - 1), indexing="ij")
        a = (jj * W + ii).ravel()
        b, d, e = a + 1, a + W, a + W + 1
        faces = np.concatenate([np.column_stack([a, b, e]), np.column_stack([a, e, d])])
        if closed:
            verts, faces = _close_solid(verts, faces, H, W, -self.thickness_mm)
        return trimesh.Trimesh(vertices=verts, faces=faces, process=False)


def _close_solid(verts, faces, H, W, z_bottom):
    """Add side walls and a bottom to a (H, W) vertex grid surface, outward-facing."""
    idx = np.arange(H * W).reshape(H, W)
    ring = np.concatenate([idx[0, :], idx[1:, -1], idx[-1, -2::-1], idx[-2:0:-1, 0]])
    n0 = len(verts)
    bottom = verts[ring].copy()
    bottom[:, 2] = z_bottom
    centre = np.array([[verts[:, 0].mean(), verts[:, 1].mean(), z_bottom]])
    verts = np.vstack([verts, bottom, centre])
    k = np.arange(len(ring))
    top_a, top_b = ring[k], ring[(k + 1) % len(ring)]
    bot_a, bot_b = n0 + k, n0 + (k + 1) % len(ring)
    walls = np.concatenate([np.column_stack([top_a, bot_a, bot_b]),
                            np.column_stack([top_a, bot_b, top_b])])
    c = len(verts) - 1
    base = np.column_stack([np.full(len(ring), c), bot_b, bot_a])
    return verts, np.concatenate([faces, walls, base])
