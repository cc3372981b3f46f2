"""Signed deviation of a measured surface mesh from the near-net reference (paper sec. 6.2).

The distance is the closest distance of each measured vertex to the reference surface (the
reference height map triangulated on its cell centres; an exact point-triangle search bounded by
the vertical distance, in a numba kernel).
Its sign comes from the side of the reference height map the vertex lies on (above: positive =
more material than the reference), never from inside/outside of an open mesh.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from dm2.defects.classify import classify_vertices, curvature_and_areas
from dm2.defects.footprint import mark_overspray
from dm2.defects.stale import stale_gap_mm
from dm2.defects.uncertainty import coefficients, uncertainty_features
from dm2.defects.uncertainty_online import inflated_sigma_mm, model_inflation
from dm2.reference.height_map import ReferenceMap

log = logging.getLogger(__name__)

MAX_SEARCH_MM = 20.0  # closest-point search radius cap (deviations beyond are vertical)


def _surface_arrays(surface):
    """``(vertices_O, faces, weight)`` of a dm2.fusion.surface.SurfaceMesh-like object,
    validated."""
    v = np.ascontiguousarray(surface.vertices_O, dtype=np.float64)
    f = np.ascontiguousarray(surface.faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"surface.vertices_O: expected (n, 3), got {v.shape}")
    if f.size and (f.ndim != 2 or f.shape[1] != 3 or f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"surface.faces: expected (m, 3) indices into {len(v)} vertices")
    f = f.reshape(-1, 3)
    w = getattr(surface, "weight", None)
    w = np.full(len(v), np.inf) if w is None else np.asarray(w, dtype=np.float64).reshape(-1)
    if w.shape[0] != v.shape[0]:
        raise ValueError(f"surface.weight: expected ({len(v)},), got {w.shape}")
    return v, f, w


@njit(cache=True, inline="always")
def closest_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest point of triangle abc to p (Ericson, Real-Time Collision Detection 5.1.5)."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3)
        return ax + t * abx, ay + t * aby, az + t * abz
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6)
        return ax + t * acx, ay + t * acy, az + t * acz
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + t * (cx - bx), by + t * (cy - by), bz + t * (cz - bz)
    den = 1.0 / (va + vb + vc)
    v = vb * den
    w = vc * den
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w


@njit(cache=True, inline="always")
def _quad_closest(px, py, pz, h, ox, oy, cell, i, j, best):
    """``best`` (squared distance, closest x, y, z) lowered by quad ``(i, j)`` of the grid
    (:func:`closest_on_grid`) where one of its triangles a-b-d, a-d-c is closer; the quad is
    skipped when its bounding box is no closer."""
    x0 = (i + ox) * cell
    y0 = (j + oy) * cell
    x1 = x0 + cell
    y1 = y0 + cell
    a, b = h[j, i], h[j, i + 1]
    c, d = h[j + 1, i], h[j + 1, i + 1]
    ex = max(x0 - px, 0.0, px - x1)
    ey = max(y0 - py, 0.0, py - y1)
    ez = max(min(a, b, c, d) - pz, 0.0, pz - max(a, b, c, d))
    if ex * ex + ey * ey + ez * ez >= best[0]:
        return best
    for t in range(2):
        if t == 0:
            cx, cy, cz = closest_on_triangle(px, py, pz, x0, y0, a, x1, y0, b, x1, y1, d)
        else:
            cx, cy, cz = closest_on_triangle(px, py, pz, x0, y0, a, x1, y1, d, x0, y1, c)
        d2 = (cx - px) ** 2 + (cy - py) ** 2 + (cz - pz) ** 2
        if d2 < best[0]:
            best = (d2, cx, cy, cz)
    return best


@njit(cache=True, parallel=True, nogil=True)
def closest_on_grid(points, h, ox, oy, cell, max_r):
    """Signed closest distance (n,) and closest points (n, 3) of ``points`` (n, 3) [mm] to
    the grid mesh of heights ``h`` (ny, nx): vertex ``(i, j)`` at ``((i + ox) cell,
    (j + oy) cell, h[j, i])`` [mm], each square split a-b-d / a-d-c (a = (i, j), b = (i + 1,
    j), c = (i, j + 1), d = (i + 1, j + 1)); the sign is the side of the surface (+ above).

    Exact within ``max_r`` [mm] of the point's vertical distance to the surface (the search
    square; ``np.inf``: exact): the squares are searched in rings around the point's own, each
    skipped where its bounding box is no closer than the best so far, the rings stopped once
    they lie farther in xy alone."""
    ny, nx = h.shape
    n = points.shape[0]
    dist = np.empty(n)
    foot = np.empty((n, 3))
    for k in prange(n):
        px, py, pz = points[k, 0], points[k, 1], points[k, 2]
        fx = min(max(px / cell - ox, 0.0), nx - 1.0)
        fy = min(max(py / cell - oy, 0.0), ny - 1.0)
        i0 = min(int(fx), nx - 2)
        j0 = min(int(fy), ny - 2)
        tx, ty = fx - i0, fy - j0
        ha, hb, hc, hd = h[j0, i0], h[j0, i0 + 1], h[j0 + 1, i0], h[j0 + 1, i0 + 1]
        if tx >= ty:  # triangle a-b-d
            hz = ha + tx * (hb - ha) + ty * (hd - hb)
        else:  # triangle a-d-c
            hz = ha + ty * (hc - ha) + tx * (hd - hc)
        side = 1.0 if pz >= hz else -1.0
        qx = (fx + ox) * cell
        qy = (fy + oy) * cell
        off = math.sqrt((qx - px) ** 2 + (qy - py) ** 2)  # outside the map: clamp distance
        best = ((pz - hz) ** 2 + off * off, qx, qy, hz)  # a point of the surface
        r = min(math.sqrt(best[0]), max_r)
        ia = max(int(math.floor((px - r) / cell - ox)), 0)
        ib = min(int(math.floor((px + r) / cell - ox)), nx - 2)
        ja = max(int(math.floor((py - r) / cell - oy)), 0)
        jb = min(int(math.floor((py + r) / cell - oy)), ny - 2)
        ring = 0
        while True:
            if ring >= 2 and ((ring - 1) * cell) ** 2 >= best[0]:
                break  # every square of this ring lies farther in xy alone
            if i0 - ring < ia and j0 - ring < ja and i0 + ring > ib and j0 + ring > jb:
                break  # the ring lies wholly outside the search square
            for j in range(max(j0 - ring, ja), min(j0 + ring, jb) + 1):
                if j == j0 - ring or j == j0 + ring:  # the ring's bottom and top rows
                    for i in range(max(i0 - ring, ia), min(i0 + ring, ib) + 1):
                        best = _quad_closest(px, py, pz, h, ox, oy, cell, i, j, best)
                else:  # its two sides (ring >= 1 here)
                    if i0 - ring >= ia:
                        best = _quad_closest(px, py, pz, h, ox, oy, cell, i0 - ring, j, best)
                    if i0 + ring <= ib:
                        best = _quad_closest(px, py, pz, h, ox, oy, cell, i0 + ring, j, best)
            ring += 1
        dist[k] = side * math.sqrt(best[0])
        foot[k, 0], foot[k, 1], foot[k, 2] = best[1], best[2], best[3]
    return dist, foot


def closest_on_reference(points_O: np.ndarray, reference: ReferenceMap):
    """Signed closest distance [mm] (n,) and closest reference points ``foot_O`` (n, 3).

    The reference surface is the map's cell-centre grid split into triangles; the search for
    the closest triangle is bounded by the vertical distance (numba, parallel over points).
    """
    p = np.ascontiguousarray(points_O, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros(0), np.zeros((0, 3))
    return closest_on_grid(p, reference.heights_mm, 0.5, 0.5, reference.cell_mm, MAX_SEARCH_MM)


def signed_deviation(surface, reference: ReferenceMap) -> np.ndarray:
    """Per-vertex signed distance [mm] (n,) of ``surface`` to ``reference``.

    Parameters
    ----------
    surface : object with ``vertices_O`` (n, 3) [mm] (e.g. dm2.fusion.surface.SurfaceMesh)
    reference : ReferenceMap, the near-net reference of the same layer / time

    Returns
    -------
    (n,) float64 [mm], positive where the part is above the reference (overbuild).
    """
    d, _ = closest_on_reference(np.asarray(surface.vertices_O, dtype=np.float64), reference)
    return d


@dataclass(frozen=True)
class LayerDeviation:
    """Deviation map of one layer (or one moment) and its per-vertex classes.

    Attributes
    ----------
    layer : int
    vertices_O : (n, 3) float64 [mm], measured surface vertices
    faces : (m, 3) int64, triangles
    weight : (n,) float64, fusion weight per vertex (observation confidence)
    signed_distance_mm : (n,) float64 [mm], + above the reference
    foot_O : (n, 3) float64 [mm], closest point on the reference per vertex
    class_code : (n,) int8, codes of dm2.defects.classify.CLASS_NAMES
    local_metric : (n,) float64, normalised curvature-weighted deviation (dimensionless)
    mean_curvature : (n,) float64 [1/mm], + convex
    vertex_area_mm2 : (n,) float64 [mm^2], barycentric area per vertex
    stamp_s : float [s]
    sigma_mm : (n,) float64 [mm] or None, standard deviation of each vertex's deviation
        (dm2.defects.uncertainty)
    outside_mm : (n,) float64 [mm] or None, distance outside the planned outline
    normals_O : (n, 3) float64 or None, unit vertex normals used for the classification
    unseen_mm : (n,) float64 [mm] or None, the reference's growth at each vertex since the
        profilers last saw it (dm2.pipeline.seen_reference): an underbuild that small is not
        measured, only not yet seen
    stale_mm : (n,) float64 [mm] or None, how far a vertex lies below the surface last seen all
        around it, beyond a margin (dm2.defects.stale): an old top the new one grew over
        unseen, not an underbuild
    model_inflation : {term: factor} or None, how far this layer's own deviations raised the
        uncertainty's model-error terms (dm2.defects.uncertainty_online)
    """

    layer: int
    vertices_O: np.ndarray
    faces: np.ndarray
    weight: np.ndarray
    signed_distance_mm: np.ndarray
    foot_O: np.ndarray
    class_code: np.ndarray
    local_metric: np.ndarray
    mean_curvature: np.ndarray
    vertex_area_mm2: np.ndarray
    stamp_s: float = 0.0
    sigma_mm: np.ndarray | None = None
    outside_mm: np.ndarray | None = None
    normals_O: np.ndarray | None = None
    unseen_mm: np.ndarray | None = None
    model_inflation: dict | None = None
    stale_mm: np.ndarray | None = None

    @property
    def n_vertices(self) -> int:
        return int(self.vertices_O.shape[0])

    def vertex_areas(self) -> np.ndarray:
        """One third of the area of every incident triangle, per vertex [mm^2] (n,)."""
        return self.vertex_area_mm2


def layer_deviation(surface, reference: ReferenceMap, monitor_cfg, layer: int | None = None,
                    stamp_s: float | None = None, outline=None,
                    uncertainty: bool = True, unseen=None,
                    seen_surface=None) -> LayerDeviation:
    """Signed deviation, uncertainty and classification of a measured surface.

    ``monitor_cfg`` supplies ``delta_global_mm``, ``delta_local``, ``min_weight``,
    ``uncertainty`` and ``overspray_margin_mm``; ``outline`` (a
    dm2.defects.footprint.PlannedOutline) enables the overspray class; ``uncertainty=False``
    classifies on the deviation alone (the paper's rule). ``unseen`` (a ReferenceMap of the
    reference's growth since each column was last observed, or None) shrinks an underbuild by
    that growth: the measurement there predates the last deposit. ``seen_surface`` (a
    dm2.defects.stale.SeenSurface, or None) shrinks it by how far a vertex lies below what the
    profilers last saw all around it (a stale top, :mod:`dm2.defects.stale`).
    """
    v, f, w = _surface_arrays(surface)
    d, foot = closest_on_reference(v, reference)
    normals = getattr(surface, "normals_O", None)
    curv = curvature_and_areas(v, f, normals, return_normals=True)
    unseen_mm = None
    if unseen is not None:
        unseen_mm = np.maximum(unseen.height_at(v[:, :2]), 0.0)
    stale_mm = stale_gap_mm(v, seen_surface, unseen_mm, curv[2])
    lifts = [x for x in (unseen_mm, stale_mm) if x is not None]
    if lifts:
        d = np.where(d < 0.0, np.minimum(d + sum(lifts), 0.0), d)
    ref_curv = reference.mean_curvature_at(foot[:, :2])
    sigma = inflation = None
    if uncertainty:
        feats = uncertainty_features(v, w, curv[2], foot, reference, ref_curv,
                                     float(monitor_cfg.min_weight))
        coef = coefficients(monitor_cfg.uncertainty)
        concave = reference.plume_sensitivity_at(foot[:, :2]) > 0.0
        inflation = model_inflation(feats, d, coef, w >= float(monitor_cfg.min_weight), concave)
        sigma = inflated_sigma_mm(feats, coef, inflation, concave)
    classes = classify_vertices(v, f, w, d, monitor_cfg, reference_curvature=ref_curv,
                                sigma_mm=sigma, curvature=curv)
    code, outside = classes.class_code, None
    if outline is not None:
        outside = outline.outside_at(v[:, :2])
        code = mark_overspray(code, d, f, outside, float(monitor_cfg.overspray_margin_mm))
    layer = reference.layer if layer is None else int(layer)
    log.debug("layer %d: %d vertices, deviation %.3f..%.3f mm", layer, len(v),
              float(d.min()) if len(d) else 0.0, float(d.max()) if len(d) else 0.0)
    return LayerDeviation(layer, v, f, w, d, foot, code, classes.local_metric,
                          classes.mean_curvature, classes.vertex_area_mm2,
                          float(reference.stamp_s if stamp_s is None else stamp_s), sigma,
                          outside, curv[2], unseen_mm, inflation, stale_mm)
