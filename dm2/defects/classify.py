"""Per-vertex classification: global and local over/underbuild, unobserved (paper sec. 6.2).

Global: ``d > delta_G`` overbuild, ``d < -delta_G`` underbuild. Inside the tolerance the local
metric is the curvature-weighted signed distance, normalised to be dimensionless:

    lambda = (d / delta_G) * min(1, max(0, sign(d) * (H - H_ref)) * LOCAL_CURVATURE_RADIUS_MM)

with ``H`` the discrete mean curvature (cotangent Laplacian, smoothed through the faces), less
the reference's own mean curvature at the closest reference point when it is given (a rounded
edge the reference has too is not a local defect). Curvature and deviation must agree in sign,
as the paper's product of the two does: a local overbuild is a bump (convex, above), a local
underbuild a dent (concave, below); a measured edge that is merely sharper or rounder than the
reference is neither. A flat offset (``H ~ 0``) is not a local defect however thick; a curved
feature (radius of curvature up to ``LOCAL_CURVATURE_RADIUS_MM``) counts with its full
normalised deviation. ``lambda > delta_L``
is local overbuild, ``lambda < -delta_L`` local underbuild. Vertices whose fusion weight is below
``min_weight`` are unobserved and never called under- or overbuilt.

Given each vertex's standard deviation ``sigma`` (:mod:`dm2.defects.uncertainty`), the
vertices beyond ``delta_global_mm`` form connected same-signed candidate regions (over mesh
edges); a region is over-/underbuilt only where at least ``MIN_CONFIDENT_AREA_MM2`` of it lies
beyond ``k sigma`` (``monitor.uncertainty.confidence_k``): the bound decides whether there is
a defect, the tolerance how far it reaches. The vertices of a region without that evidence are
``uncertain``: reported and coloured, never segmented into a defect region (unless their local
metric makes them a local defect). The local classes keep the paper's rule: they are early
warnings, which open a track only together with a global observation of the region
(dm2.defects.track).
``overspray`` (:mod:`dm2.defects.footprint`) marks deviations on the plate outside the planned
outline that are not joined to a defect at a wall; they are reported, never tracked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from dm2.core.tolerances import DIVISOR_FLOOR, NEAR_ZERO, RELATIVE_LENGTH_ZERO

(NORMAL, OVERBUILD, UNDERBUILD, LOCAL_OVERBUILD, LOCAL_UNDERBUILD, UNOBSERVED, UNCERTAIN,
 OVERSPRAY) = range(8)
CLASS_NAMES = ("normal", "overbuild", "underbuild", "local_overbuild", "local_underbuild",
               "unobserved", "uncertain", "overspray")
DEFECT_CLASSES = (OVERBUILD, UNDERBUILD, LOCAL_OVERBUILD, LOCAL_UNDERBUILD)
LOCAL_CURVATURE_RADIUS_MM = 10.0
MIN_CONFIDENT_AREA_MM2 = 1.0  # of a candidate region beyond k sigma: it is a defect
CURVATURE_SMOOTHING_ITERATIONS = 3


@dataclass(frozen=True)
class VertexClasses:
    """Result of :func:`classify_vertices`.

    Attributes
    ----------
    class_code : (n,) int8, index into ``CLASS_NAMES``
    local_metric : (n,) float64, normalised curvature-weighted deviation (dimensionless)
    mean_curvature : (n,) float64 [1/mm], positive where convex (a bump seen from above)
    vertex_area_mm2 : (n,) float64 [mm^2], barycentric area per vertex
    normals_O : (n, 3) float64, unit vertex normals (given, or area-weighted face normals)
    """

    class_code: np.ndarray
    local_metric: np.ndarray
    mean_curvature: np.ndarray
    vertex_area_mm2: np.ndarray
    normals_O: np.ndarray | None = None


@njit(cache=True, nogil=True)
def _face_terms(v, faces):
    """One pass over the faces: cotangent Laplacian ``sum_j w_ij (v_j - v_i)``, barycentric
    vertex areas, area-weighted normals and the sum of the edges opposite each vertex (zero
    around an interior vertex of a consistently oriented mesh)."""
    n = v.shape[0]
    lap = np.zeros((n, 3))
    area = np.zeros(n)
    nrm = np.zeros((n, 3))
    loop = np.zeros((n, 3))
    for f in range(faces.shape[0]):
        ia, ib, ic = faces[f, 0], faces[f, 1], faces[f, 2]
        e0x, e0y, e0z = v[ib, 0] - v[ia, 0], v[ib, 1] - v[ia, 1], v[ib, 2] - v[ia, 2]  # a->b
        e1x, e1y, e1z = v[ic, 0] - v[ib, 0], v[ic, 1] - v[ib, 1], v[ic, 2] - v[ib, 2]  # b->c
        e2x, e2y, e2z = v[ia, 0] - v[ic, 0], v[ia, 1] - v[ic, 1], v[ia, 2] - v[ic, 2]  # c->a
        cx = e0y * (-e2z) - e0z * (-e2y)
        cy = e0z * (-e2x) - e0x * (-e2z)
        cz = e0x * (-e2y) - e0y * (-e2x)
        dbl = math.sqrt(cx * cx + cy * cy + cz * cz)
        if dbl < NEAR_ZERO:
            continue
        # corner a weights edge b->c, corner b edge c->a, corner c edge a->b (cot / 2)
        wa = -0.5 * (e0x * e2x + e0y * e2y + e0z * e2z) / dbl
        wb = -0.5 * (e1x * e0x + e1y * e0y + e1z * e0z) / dbl
        wc = -0.5 * (e2x * e1x + e2y * e1y + e2z * e1z) / dbl
        for c, (x0, x1, x2) in enumerate(((e0x, e1x, e2x), (e0y, e1y, e2y), (e0z, e1z, e2z))):
            lap[ib, c] += wa * x1
            lap[ic, c] -= wa * x1
            lap[ic, c] += wb * x2
            lap[ia, c] -= wb * x2
            lap[ia, c] += wc * x0
            lap[ib, c] -= wc * x0
            loop[ia, c] += x1
            loop[ib, c] += x2
            loop[ic, c] += x0
        for i in (ia, ib, ic):
            nrm[i, 0] += cx
            nrm[i, 1] += cy
            nrm[i, 2] += cz
            area[i] += dbl / 6.0
    return lap, area, nrm, loop


@njit(cache=True, nogil=True)
def _smooth(values, faces, iterations):
    n = values.shape[0]
    count = np.zeros(n)
    for f in range(faces.shape[0]):
        for k in range(3):
            count[faces[f, k]] += 1.0
    out = values.copy()
    for _ in range(iterations):
        acc = np.zeros(n)
        for f in range(faces.shape[0]):
            m = (out[faces[f, 0]] + out[faces[f, 1]] + out[faces[f, 2]]) / 3.0
            for k in range(3):
                acc[faces[f, k]] += m
        for i in range(n):
            if count[i] > 0:
                out[i] = acc[i] / count[i]
    return out


def vertex_areas(vertices_O: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Barycentric vertex areas [mm^2] (n,): a third of each incident triangle."""
    v = np.ascontiguousarray(vertices_O, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    return _face_terms(v, f)[1] if len(f) else np.zeros(len(v))


def boundary_vertices(vertices_O: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n,) bool, vertices on the border of a consistently oriented triangle mesh.

    Around an interior vertex the edges opposite to it close a loop, so their vectors sum to
    zero; at a border vertex the loop is open.
    """
    v = np.ascontiguousarray(vertices_O, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    return _border(v, f, _face_terms(v, f)[3])


def _border(v, f, loop) -> np.ndarray:
    scale = np.linalg.norm(v[f[:, 1]] - v[f[:, 0]], axis=1).mean() if len(f) else 1.0
    return np.linalg.norm(loop, axis=1) > RELATIVE_LENGTH_ZERO * scale


def curvature_and_areas(vertices_O: np.ndarray, faces: np.ndarray, normals_O=None,
                        smooth_iterations: int = CURVATURE_SMOOTHING_ITERATIONS,
                        return_normals: bool = False):
    """``(mean curvature [1/mm] (n,), vertex areas [mm^2] (n,))`` of a triangle mesh, and the
    unit normals (n, 3) used for the sign with ``return_normals``.

    Mean curvature by the cotangent Laplacian, + where convex, 0 on the border of an open
    mesh, then smoothed through the faces. The sign is taken against ``normals_O`` when given,
    else against the area-weighted face normals.
    """
    v = np.ascontiguousarray(vertices_O, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    n = len(v)
    if len(f) == 0:
        flat = np.tile([0.0, 0.0, 1.0], (n, 1))
        return (np.zeros(n), np.zeros(n), flat) if return_normals else (np.zeros(n), np.zeros(n))
    lap, area, nrm, loop = _face_terms(v, f)
    hn = lap / np.maximum(area, DIVISOR_FLOOR)[:, None]  # = 2 H n (points into a convex surface)
    normals = nrm if normals_O is None else np.asarray(normals_O, dtype=np.float64)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), DIVISOR_FLOOR)
    h = -0.5 * np.einsum("ij,ij->i", hn, normals)
    h[_border(v, f, loop)] = 0.0
    h[area <= NEAR_ZERO] = 0.0
    h = _smooth(h, f, int(smooth_iterations))
    return (h, area, normals) if return_normals else (h, area)


def mean_curvature(vertices_O: np.ndarray, faces: np.ndarray, normals_O=None,
                   smooth_iterations: int = CURVATURE_SMOOTHING_ITERATIONS) -> np.ndarray:
    """Discrete mean curvature [1/mm] (n,) (see :func:`curvature_and_areas`)."""
    return curvature_and_areas(vertices_O, faces, normals_O, smooth_iterations)[0]


def classify_vertices(vertices_O, faces, weight, signed_distance_mm, monitor_cfg,
                      normals_O=None, reference_curvature=None, sigma_mm=None,
                      curvature=None) -> VertexClasses:
    """Class per vertex from the signed deviation (see module docstring).

    Parameters
    ----------
    vertices_O : (n, 3) float64 [mm]
    faces : (m, 3) int64
    weight : (n,) float64, fusion weight
    signed_distance_mm : (n,) float64 [mm]
    monitor_cfg : has ``delta_global_mm``, ``delta_local``, ``min_weight``
    normals_O : (n, 3) float64 or None, outward vertex normals (sign of the curvature)
    reference_curvature : (n,) float64 [1/mm] or None, the reference's mean curvature at each
        vertex's closest reference point; only curvature beyond it weights the local metric
    sigma_mm : (n,) float64 [mm] or None, standard deviation of each deviation; with it a
        global class needs ``|d| > monitor_cfg.uncertainty.confidence_k * sigma`` too
    curvature : ``curvature_and_areas(..., return_normals=True)`` when computed already
    """
    d = np.asarray(signed_distance_mm, dtype=np.float64)
    w = np.asarray(weight, dtype=np.float64)
    dg = float(monitor_cfg.delta_global_mm)
    dl = float(monitor_cfg.delta_local)
    h, area, normals = (curvature if curvature is not None else
                        curvature_and_areas(vertices_O, faces, normals_O, return_normals=True))
    excess = h if reference_curvature is None else h - np.asarray(reference_curvature, float)
    agree = np.maximum(np.sign(d) * excess, 0.0)  # convex where above, concave where below
    metric = (d / dg) * np.minimum(1.0, agree * LOCAL_CURVATURE_RADIUS_MM)
    beyond = np.ones(d.shape, bool) if sigma_mm is None else _confident_regions(
        d, dg, np.abs(d) > float(monitor_cfg.uncertainty.confidence_k)
        * np.asarray(sigma_mm, np.float64), area, faces)
    code = np.full(d.shape, NORMAL, dtype=np.int8)
    code[(d > dg) & ~beyond] = UNCERTAIN
    code[(d < -dg) & ~beyond] = UNCERTAIN
    code[metric > dl] = LOCAL_OVERBUILD
    code[metric < -dl] = LOCAL_UNDERBUILD
    code[(d > dg) & beyond] = OVERBUILD
    code[(d < -dg) & beyond] = UNDERBUILD
    code[w < float(monitor_cfg.min_weight)] = UNOBSERVED
    return VertexClasses(code, metric, h, area, normals)


def _confident_regions(d, dg, strong, area, faces) -> np.ndarray:
    """(n,) bool: vertices of same-signed connected regions beyond ``+-dg`` holding at least
    ``MIN_CONFIDENT_AREA_MM2`` of ``strong`` (beyond the bound) vertices."""
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components

    n = len(d)
    cand = np.abs(d) > dg
    out = np.zeros(n, bool)
    ids = np.flatnonzero(cand)
    if ids.size == 0:
        return out
    local = np.full(n, -1, np.int64)
    local[ids] = np.arange(ids.size)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    f = f[cand[f].any(axis=1)]  # faces touching a candidate: the only edges that matter
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e = e[cand[e[:, 0]] & cand[e[:, 1]] & (np.sign(d[e[:, 0]]) == np.sign(d[e[:, 1]]))]
    m = ids.size
    graph = sparse.coo_matrix((np.ones(len(e), np.int8), (local[e[:, 0]], local[e[:, 1]])),
                              shape=(m, m))
    _, labels = connected_components(graph, directed=False)
    a = np.where(strong[ids], np.maximum(area[ids], 1e-3), 0.0)  # isolated points count a bit
    strong_area = np.bincount(labels, a, minlength=labels.max() + 1)
    out[ids] = strong_area[labels] >= MIN_CONFIDENT_AREA_MM2
    return out
