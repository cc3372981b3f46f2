"""Per-vertex classification: global and local over/underbuild, unobserved (paper sec. 6.2).

Global: ``d > delta_G`` overbuild, ``d < -delta_G`` underbuild. Inside the tolerance the local
metric is the curvature-weighted signed distance, normalised to be dimensionless:

    lambda = (d / delta_G) * min(1, |H| * LOCAL_CURVATURE_RADIUS_MM)

with ``H`` the discrete mean curvature (cotangent Laplacian, smoothed over the 1-ring). A flat
offset (``H ~ 0``) is not a local defect however thick; a curved feature (radius of curvature up
to ``LOCAL_CURVATURE_RADIUS_MM``) counts with its full normalised deviation. ``lambda > delta_L``
is local overbuild, ``lambda < -delta_L`` local underbuild. Vertices whose fusion weight is below
``min_weight`` are unobserved and never called under- or overbuilt.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

NORMAL, OVERBUILD, UNDERBUILD, LOCAL_OVERBUILD, LOCAL_UNDERBUILD, UNOBSERVED = range(6)
CLASS_NAMES = ("normal", "overbuild", "underbuild", "local_overbuild", "local_underbuild",
               "unobserved")
DEFECT_CLASSES = (OVERBUILD, UNDERBUILD, LOCAL_OVERBUILD, LOCAL_UNDERBUILD)
LOCAL_CURVATURE_RADIUS_MM = 10.0
CURVATURE_SMOOTHING_ITERATIONS = 3


@dataclass(frozen=True)
class VertexClasses:
    """Result of :func:`classify_vertices`.

    Attributes
    ----------
    class_code : (n,) int8, index into ``CLASS_NAMES``
    local_metric : (n,) float64, normalised curvature-weighted deviation (dimensionless)
    mean_curvature : (n,) float64 [1/mm], positive where convex (a bump seen from above)
    """

    class_code: np.ndarray
    local_metric: np.ndarray
    mean_curvature: np.ndarray


def vertex_adjacency(n: int, faces: np.ndarray) -> sparse.csr_matrix:
    """Symmetric (n, n) 0/1 vertex adjacency of a triangle mesh."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    a = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    a = ((a + a.T) > 0).astype(np.float64)
    return a


def boundary_vertices(n: int, faces: np.ndarray) -> np.ndarray:
    """(n,) bool, vertices on an edge used by a single triangle."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    key = e[:, 0].astype(np.int64) * n + e[:, 1]
    uniq, count = np.unique(key, return_counts=True)
    once = uniq[count == 1]
    out = np.zeros(n, bool)
    out[once // n] = True
    out[once % n] = True
    return out


def mean_curvature(vertices_O: np.ndarray, faces: np.ndarray, normals_O=None,
                   smooth_iterations: int = CURVATURE_SMOOTHING_ITERATIONS) -> np.ndarray:
    """Discrete mean curvature [1/mm] (n,) by the cotangent Laplacian, + where convex.

    Boundary vertices of an open mesh get 0. The sign is taken against ``normals_O`` when given,
    else against the area-weighted face normals.
    """
    v = np.asarray(vertices_O, dtype=np.float64)
    n = len(v)
    if len(faces) == 0:
        return np.zeros(n)
    tri = v[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    dbl_area = np.maximum(np.linalg.norm(cross, axis=1), 1e-12)
    rows, cols, vals = [], [], []
    for k in range(3):  # corner k: cotangent weights the opposite edge (i, j)
        i, j = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]
        a = v[i] - v[faces[:, k]]
        b = v[j] - v[faces[:, k]]
        cot = np.einsum("ij,ij->i", a, b) / dbl_area
        rows += [i, j]
        cols += [j, i]
        vals += [0.5 * cot, 0.5 * cot]
    w = sparse.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(n, n)).tocsr()
    lap = w @ v - np.asarray(w.sum(axis=1)).reshape(-1, 1) * v  # sum_j w_ij (v_j - v_i)
    area = np.bincount(faces.ravel(), np.repeat(dbl_area / 6.0, 3), minlength=n)
    hn = lap / np.maximum(area, 1e-12)[:, None]  # = 2 H n (points into a convex surface)
    if normals_O is None:
        normals = np.zeros((n, 3))
        for k in range(3):
            np.add.at(normals, faces[:, k], cross)
    else:
        normals = np.asarray(normals_O, dtype=np.float64)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    h = -0.5 * np.einsum("ij,ij->i", hn, normals)
    h[boundary_vertices(n, faces)] = 0.0
    h[area <= 1e-12] = 0.0
    if smooth_iterations > 0:
        adj = vertex_adjacency(n, faces) + sparse.identity(n, format="csr")
        deg = np.asarray(adj.sum(axis=1)).reshape(-1)
        for _ in range(smooth_iterations):
            h = (adj @ h) / deg
    return h


def classify_vertices(vertices_O, faces, weight, signed_distance_mm, monitor_cfg,
                      normals_O=None) -> VertexClasses:
    """Class per vertex from the signed deviation (see module docstring).

    Parameters
    ----------
    vertices_O : (n, 3) float64 [mm]
    faces : (m, 3) int64
    weight : (n,) float64, fusion weight
    signed_distance_mm : (n,) float64 [mm]
    monitor_cfg : has ``delta_global_mm``, ``delta_local``, ``min_weight``
    """
    d = np.asarray(signed_distance_mm, dtype=np.float64)
    w = np.asarray(weight, dtype=np.float64)
    dg = float(monitor_cfg.delta_global_mm)
    dl = float(monitor_cfg.delta_local)
    h = mean_curvature(vertices_O, np.asarray(faces, dtype=np.int64), normals_O)
    metric = (d / dg) * np.minimum(1.0, np.abs(h) * LOCAL_CURVATURE_RADIUS_MM)
    code = np.full(d.shape, NORMAL, dtype=np.int8)
    code[metric > dl] = LOCAL_OVERBUILD
    code[metric < -dl] = LOCAL_UNDERBUILD
    code[d > dg] = OVERBUILD
    code[d < -dg] = UNDERBUILD
    code[w < float(monitor_cfg.min_weight)] = UNOBSERVED
    return VertexClasses(code, metric, h)
