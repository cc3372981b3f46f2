"""The reference surface as a height map over the plate, with its SDF and mesh views."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit


@dataclass(frozen=True)
class ReferenceMap:
    """Near-net reference surface ``z_O = h(x, y)`` on a regular grid in ``O``.

    Attributes
    ----------
    heights_mm : (ny, nx) float64 [mm], reference top surface at cell centres
        ``((i + 0.5) * cell_mm, (j + 0.5) * cell_mm)`` for row ``j``, column ``i`` (0 = plate)
    cell_mm : float [mm], grid spacing
    layer : int, the layer this reference belongs to
    stamp_s : float [s], process time of the last robot state integrated
    plume_sigma_mm : float [mm], the plume width the model deposited with (0: not known)
    """

    heights_mm: np.ndarray
    cell_mm: float
    layer: int = 0
    stamp_s: float = 0.0
    plume_sigma_mm: float = 0.0

    def __post_init__(self):
        h = np.ascontiguousarray(self.heights_mm, dtype=np.float64)
        if h.ndim != 2 or min(h.shape) < 2:
            raise ValueError(f"ReferenceMap.heights_mm: expected (ny, nx) >= 2, got {h.shape}")
        if not np.all(np.isfinite(h)):
            raise ValueError("ReferenceMap.heights_mm: contains NaN or infinite values")
        if not self.cell_mm > 0:
            raise ValueError(f"ReferenceMap.cell_mm: must be positive, got {self.cell_mm}")
        h.setflags(write=False)
        object.__setattr__(self, "heights_mm", h)
        object.__setattr__(self, "cell_mm", float(self.cell_mm))

    @property
    def size_mm(self) -> tuple[float, float]:
        ny, nx = self.heights_mm.shape
        return nx * self.cell_mm, ny * self.cell_mm

    def _frac(self, xy_O: np.ndarray):
        return _cell_fractions(self.heights_mm.shape, self.cell_mm, xy_O)

    def height_at(self, xy_O) -> np.ndarray:
        """Bilinear reference height [mm] at ``xy_O`` (n, 2); clamped at the map's border."""
        return bilinear_height(self.heights_mm, self.cell_mm, xy_O)

    def gradient_at(self, xy_O) -> np.ndarray:
        """``(dh/dx, dh/dy)`` (n, 2) of the bilinear surface at ``xy_O``."""
        xy = np.asarray(xy_O, dtype=np.float64).reshape(-1, 2)
        h = self.heights_mm
        i0, j0, tx, ty = self._frac(xy)
        gx = ((1 - ty) * (h[j0, i0 + 1] - h[j0, i0]) + ty * (h[j0 + 1, i0 + 1] - h[j0 + 1, i0]))
        gy = ((1 - tx) * (h[j0 + 1, i0] - h[j0, i0]) + tx * (h[j0 + 1, i0 + 1] - h[j0, i0 + 1]))
        return np.stack([gx, gy], axis=1) / self.cell_mm

    def normals_at(self, xy_O) -> np.ndarray:
        """Unit upward normals (n, 3) of the reference surface at ``xy_O``."""
        g = self.gradient_at(xy_O)
        n = np.column_stack([-g[:, 0], -g[:, 1], np.ones(len(g))])
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def smoothed_heights(self, smooth_mm: float = 0.75) -> np.ndarray:
        """The height map after a Gaussian smoothing of ``smooth_mm`` [mm] (ny, nx), computed
        once per width: the layer analysis takes curvature and plume sensitivity from it."""
        from scipy.ndimage import gaussian_filter

        cache = self.__dict__.setdefault("_smoothed", {})  # frozen: filled in place
        if smooth_mm not in cache:
            cache[smooth_mm] = gaussian_filter(self.heights_mm, smooth_mm / self.cell_mm,
                                               mode="nearest")
        return cache[smooth_mm]

    def mean_curvature_at(self, xy_O, smooth_mm: float = 0.75) -> np.ndarray:
        """Mean curvature [1/mm] (n,) of the reference surface at ``xy_O``, + where convex.

        From the height map's derivatives after a Gaussian smoothing of ``smooth_mm``.
        """
        h = self.smoothed_heights(smooth_mm)
        hy, hx = np.gradient(h, self.cell_mm)
        hxy, hxx = np.gradient(hx, self.cell_mm)
        hyy, _ = np.gradient(hy, self.cell_mm)
        num = (1 + hy * hy) * hxx - 2 * hx * hy * hxy + (1 + hx * hx) * hyy
        curv = -num / (2.0 * (1 + hx * hx + hy * hy) ** 1.5)
        return bilinear_height(curv, self.cell_mm, xy_O)

    def plume_sensitivity_at(self, xy_O, smooth_mm: float = 0.75) -> np.ndarray:
        """``dh / d ln(sigma)`` [mm] (n,) at ``xy_O``: how much the reference moves per unit
        relative change of its plume width, ``sigma^2 * laplacian(h)``.

        A Gaussian footprint of width ``sigma`` is a heat kernel, so the reference's height
        field obeys ``dh / d(sigma^2) = laplacian(h) / 2`` wherever it is a sum of such
        footprints: a plume a fraction ``r`` wider lowers convex edges and raises the foot of
        walls and concave corners by ``r sigma^2 laplacian(h)``, and leaves flat tops alone.
        Zero where the plume width is not known.
        """
        from scipy.ndimage import laplace

        if not self.plume_sigma_mm > 0:
            return np.zeros(len(np.asarray(xy_O).reshape(-1, 2)))
        h = self.smoothed_heights(smooth_mm)
        lap = laplace(h, mode="nearest") / (self.cell_mm * self.cell_mm)
        return self.plume_sigma_mm ** 2 * bilinear_height(lap, self.cell_mm, xy_O)

    def resampled(self, cell_mm: float) -> ReferenceMap:
        """The surface point-sampled on a grid of ``cell_mm`` (centres at ``(i + 0.5) * cell``).

        With ``cell_mm`` the TSDF voxel this is the reference as the measurement sees it: a
        marching-cubes surface of the SDF ``z - h`` sampled at voxel centres crosses every
        vertical voxel edge exactly at ``h`` of that column and is linear in between, i.e. it
        is this grid triangulated.
        """
        nx = max(int(round(self.size_mm[0] / cell_mm)), 2)
        ny = max(int(round(self.size_mm[1] / cell_mm)), 2)
        xx, yy = np.meshgrid((np.arange(nx) + 0.5) * cell_mm, (np.arange(ny) + 0.5) * cell_mm)
        h = self.height_at(np.column_stack([xx.ravel(), yy.ravel()])).reshape(ny, nx)
        return ReferenceMap(h, cell_mm, self.layer, self.stamp_s, self.plume_sigma_mm)

    def crop_indices(self, lo_xy, hi_xy, margin_mm: float = 0.0):
        """Row and column index slices covering ``[lo, hi]`` (+ margin) in ``O`` [mm]."""
        ny, nx = self.heights_mm.shape
        i0 = int(np.clip(np.floor((lo_xy[0] - margin_mm) / self.cell_mm - 0.5), 0, nx - 2))
        j0 = int(np.clip(np.floor((lo_xy[1] - margin_mm) / self.cell_mm - 0.5), 0, ny - 2))
        i1 = int(np.clip(np.ceil((hi_xy[0] + margin_mm) / self.cell_mm - 0.5), i0 + 1, nx - 1))
        j1 = int(np.clip(np.ceil((hi_xy[1] + margin_mm) / self.cell_mm - 0.5), j0 + 1, ny - 1))
        return slice(j0, j1 + 1), slice(i0, i1 + 1)

    def mesh_arrays(self, rows: slice | None = None, cols: slice | None = None):
        """Triangulated grid of cell centres: ``(vertices_O (n, 3), faces (m, 3) int64)``."""
        rows = rows or slice(0, self.heights_mm.shape[0])
        cols = cols or slice(0, self.heights_mm.shape[1])
        h = self.heights_mm[rows, cols]
        ny, nx = h.shape
        x = (np.arange(cols.start, cols.start + nx) + 0.5) * self.cell_mm
        y = (np.arange(rows.start, rows.start + ny) + 0.5) * self.cell_mm
        xx, yy = np.meshgrid(x, y)
        verts = np.column_stack([xx.ravel(), yy.ravel(), h.ravel()])
        idx = np.arange(nx * ny).reshape(ny, nx)
        a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        faces = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
        return verts, faces.astype(np.int64)

    def to_mesh(self):
        """The reference top surface as a ``trimesh.Trimesh`` in ``O`` (for STL export)."""
        import trimesh

        verts, faces = self.mesh_arrays()
        return trimesh.Trimesh(verts, faces, process=False)


def _cell_fractions(shape, cell_mm: float, xy_O: np.ndarray):
    ny, nx = shape
    fx = np.clip(xy_O[:, 0] / cell_mm - 0.5, 0.0, nx - 1.0)
    fy = np.clip(xy_O[:, 1] / cell_mm - 0.5, 0.0, ny - 1.0)
    i0 = np.minimum(fx.astype(np.int64), nx - 2)
    j0 = np.minimum(fy.astype(np.int64), ny - 2)
    return i0, j0, fx - i0, fy - j0


def bilinear_height(heights_mm: np.ndarray, cell_mm: float, xy_O) -> np.ndarray:
    """Bilinear interpolation [mm] (n,) of a cell-centred height grid (ny, nx) at ``xy_O``."""
    xy = np.asarray(xy_O, dtype=np.float64).reshape(-1, 2)
    return _bilinear_points(np.asarray(heights_mm, np.float64), float(cell_mm), xy)


@njit(cache=True, inline="always")
def bilinear_at(heights_mm, cell_mm, x, y):
    """Bilinear height [mm] of a cell-centred grid (ny, nx) at one point ``(x, y)`` [mm],
    clamped at the grid's border (the kernel behind :func:`bilinear_height`, for compiled
    callers)."""
    ny, nx = heights_mm.shape
    fx = min(max(x / cell_mm - 0.5, 0.0), nx - 1.0)
    fy = min(max(y / cell_mm - 0.5, 0.0), ny - 1.0)
    i0 = min(np.int64(fx), nx - 2)
    j0 = min(np.int64(fy), ny - 2)
    tx, ty = fx - i0, fy - j0
    return ((1 - tx) * (1 - ty) * heights_mm[j0, i0] + tx * (1 - ty) * heights_mm[j0, i0 + 1]
            + (1 - tx) * ty * heights_mm[j0 + 1, i0] + tx * ty * heights_mm[j0 + 1, i0 + 1])


@njit(cache=True, nogil=True)
def _bilinear_points(heights_mm, cell_mm, xy):
    out = np.empty(xy.shape[0])
    for k in range(xy.shape[0]):
        out[k] = bilinear_at(heights_mm, cell_mm, xy[k, 0], xy[k, 1])
    return out


@njit(cache=True, inline="always")
def cell_of(x_mm, y_mm, cell_mm, ny, nx):
    """(row, column) of the grid cell holding ``(x_mm, y_mm)``, or (-1, -1) off the grid (NaN
    included)."""
    x, y = x_mm / cell_mm, y_mm / cell_mm
    if not (x >= 0.0 and y >= 0.0 and x < nx and y < ny):
        return -1, -1
    return int(math.floor(y)), int(math.floor(x))
