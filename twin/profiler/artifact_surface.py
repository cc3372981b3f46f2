"""The sphere artifact as a solid the virtual profilers can scan: spheres on posts on a plate.

A height field cannot hold a sphere's undercut, so the calibration run is cast on this analytic
solid instead, through the profiler's generic surface path
(:func:`twin.profiler.numpy_path.trace_reference`): the same fan, measuring range, camera
occlusion, grazing-angle intensity floor and noise stages as a build, on exact ray/solid
intersections. The solid is given in its own frame ``A`` (the plate top is ``z_A = 0``, the
plate fills ``[0, Lx] x [0, Ly] x [-thickness, 0]``), posed in the base by the ``T_B_O`` the
profiler is handed.

This is the twin's own model of the artifact; it knows the artifact as built (its true sphere
radii and centres), which may differ from the certificate the calibration is given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2.core.tolerances import NEAR_ZERO, SAME_POINT_MM


@dataclass(frozen=True)
class SphereArtifactSurface:
    """Spheres on vertical posts standing on a rectangular plate, in frame ``A`` [mm].

    Attributes
    ----------
    centers_A : (k, 3) float64, true sphere centres
    radii_mm : (k,) float64, true sphere radii
    post_radii_mm : (k,) float64, radius of the post from the plate top to each centre (0: none)
    plate_size_mm : (3,) float64, plate length x, length y, thickness
    """

    centers_A: np.ndarray
    radii_mm: np.ndarray
    post_radii_mm: np.ndarray
    plate_size_mm: np.ndarray

    def __post_init__(self):
        c = np.asarray(self.centers_A, dtype=np.float64).reshape(-1, 3)
        r = np.asarray(self.radii_mm, dtype=np.float64).reshape(-1)
        p = np.asarray(self.post_radii_mm, dtype=np.float64).reshape(-1)
        s = np.asarray(self.plate_size_mm, dtype=np.float64).reshape(-1)
        if not (c.shape[0] == r.size == p.size) or r.size == 0 or s.size != 3:
            raise ValueError("SphereArtifactSurface: centres, radii and posts disagree in "
                             "length, or plate_size_mm is not (Lx, Ly, thickness)")
        if np.any(r <= 0) or np.any(p < 0) or np.any(s <= 0):
            raise ValueError("SphereArtifactSurface: radii and plate size must be positive")
        for name, val in (("centers_A", c), ("radii_mm", r), ("post_radii_mm", p),
                          ("plate_size_mm", s)):
            object.__setattr__(self, name, val)

    # the attributes the profiler's generic path reads
    @property
    def size_mm(self) -> np.ndarray:
        return self.plate_size_mm[:2]

    @property
    def thickness_mm(self) -> float:
        return float(self.plate_size_mm[2])

    def raycast(self, origins_A: np.ndarray, dirs_A: np.ndarray,
                max_range_mm: float = np.inf) -> np.ndarray:
        """Distance (n,) [mm] along unit rays to the first hit of the solid (inf: none within
        ``max_range_mm``)."""
        o = np.asarray(origins_A, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(dirs_A, dtype=np.float64).reshape(-1, 3)
        t = self._plate_t(o, d)
        for c, r, pr in zip(self.centers_A, self.radii_mm, self.post_radii_mm, strict=True):
            t = np.minimum(t, _sphere_t(o, d, c, r))
            if pr > 0:
                t = np.minimum(t, _post_t(o, d, c, pr))
        return np.where(t <= max_range_mm, t, np.inf)

    def solid_normals_at(self, points_A: np.ndarray) -> np.ndarray:
        """Outward unit normals (m, 3) at surface points: those of the nearest primitive."""
        p = np.asarray(points_A, dtype=np.float64).reshape(-1, 3)
        best = np.full(p.shape[0], np.inf)
        normals = np.zeros_like(p)
        for c, r, pr in zip(self.centers_A, self.radii_mm, self.post_radii_mm, strict=True):
            v = p - c
            dist = np.linalg.norm(v, axis=1)
            gap = np.abs(dist - r)
            take = gap < best
            normals[take] = v[take] / np.maximum(dist[take, None], SAME_POINT_MM)
            best = np.where(take, gap, best)
            if pr > 0:
                radial = p[:, :2] - c[:2]
                rad = np.linalg.norm(radial, axis=1)
                gap = np.where((p[:, 2] >= 0) & (p[:, 2] <= c[2]), np.abs(rad - pr), np.inf)
                take = gap < best
                normals[take] = np.column_stack([radial[take] / np.maximum(rad[take, None],
                                                                           SAME_POINT_MM),
                                                 np.zeros(int(take.sum()))])
                best = np.where(take, gap, best)
        lx, ly, th = self.plate_size_mm
        gaps = np.abs(np.column_stack([p[:, 2], p[:, 0], lx - p[:, 0], p[:, 1], ly - p[:, 1],
                                       p[:, 2] + th]))
        faces = np.array([[0, 0, 1.0], [-1.0, 0, 0], [1.0, 0, 0], [0, -1.0, 0], [0, 1.0, 0],
                          [0, 0, -1.0]])
        j = np.argmin(gaps, axis=1)
        take = gaps[np.arange(p.shape[0]), j] < best
        normals[take] = faces[j[take]]
        return normals

    def _plate_t(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        lo = np.array([0.0, 0.0, -self.plate_size_mm[2]])
        hi = np.array([self.plate_size_mm[0], self.plate_size_mm[1], 0.0])
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t1, t2 = (lo - o) * inv, (hi - o) * inv
        t1 = np.nan_to_num(t1, nan=-np.inf)
        t2 = np.nan_to_num(t2, nan=np.inf)
        t_in = np.max(np.minimum(t1, t2), axis=1)
        t_out = np.min(np.maximum(t1, t2), axis=1)
        hit = (t_out >= np.maximum(t_in, 0.0)) & (t_out > SAME_POINT_MM)
        return np.where(hit, np.where(t_in > SAME_POINT_MM, t_in, 0.0), np.inf)


def _sphere_t(o, d, center, radius) -> np.ndarray:
    oc = o - center
    b = np.einsum("ij,ij->i", oc, d)
    c = np.einsum("ij,ij->i", oc, oc) - radius * radius
    disc = b * b - c
    s = np.sqrt(np.where(disc >= 0, disc, 0.0))
    t0, t1 = -b - s, -b + s
    # an origin inside the sphere (t0 behind, t1 ahead) is blocked at once
    t = np.where(t0 > SAME_POINT_MM, t0, np.where(t1 > SAME_POINT_MM, 0.0, np.inf))
    return np.where(disc >= 0, t, np.inf)


def _post_t(o, d, center, radius) -> np.ndarray:
    """Side of the vertical post from ``z_A = 0`` up to the sphere centre."""
    ox, oy = o[:, 0] - center[0], o[:, 1] - center[1]
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = ox * d[:, 0] + oy * d[:, 1]
    c = ox * ox + oy * oy - radius * radius
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = b * b - a * c
        ok = (disc >= 0) & (a > NEAR_ZERO)
        t = np.where(ok, (-b - np.sqrt(np.where(ok, disc, 0.0))) / np.where(ok, a, 1.0), np.inf)
    z = o[:, 2] + t * d[:, 2]
    hit = ok & (t > SAME_POINT_MM) & (z >= 0.0) & (z <= center[2])
    return np.where(hit, t, np.inf)
