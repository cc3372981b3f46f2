"""Per-vertex classification: global and local over/underbuild, unobserved (paper sec. 6.2).

Global: ``d > delta_G`` overbuild, ``d < -delta_G`` underbuild. Inside the tolerance the local
metric is the curvature-weighted signed distance, normalised to be dimensionless:

    lambda = (d / delta_G) * min(1, max(0, sign(d) * (H - H_ref)) * LOCAL_CURVATURE_RADIUS_MM)

with ``H`` the discrete mean curvature (cotangent Laplacian, smoothed through the faces), less
the reference's own mean curvature at the closest reference point when it is given (a rounded
edge the reference has too is not a local defect). Curvature and deviation must agree in sign,
as the paper's product of the two does: a local overbuild is a bump (convex, above), a local
underbuild a dent (concave, below); a measured edge that is merely sharper or rounder than the
reference is neither. A flat
offset (``H ~ 0``) is not a local defect however thick; a curved feature (radius of curvature up
to ``LOCAL_CURVATURE_RADIUS_MM``) counts with its full normalised deviation. ``lambda > delta_L``
is local overbuild, ``lambda < -delta_L`` local underbuild. Vertices whose fusion weight is below
``min_weight`` are unobserved and never called under- or overbuilt.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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


def _accumulate(n: int, faces: np.ndarray, per_corner: list) -> np.ndarray:
    """Sum (m, 3) vectors given per face corner into (n, 3) per-vertex sums."""
    idx = faces.T.ravel()
    vals = np.concatenate(per_corner)
    return np.column_stack([np.bincount(idx, vals[:, c], minlength=n) for c in range(3)])


def boundary_vertices(vertices_O: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n,) bool, vertices on the border of a consistently oriented triangle mesh.

    Around an interior vertex the edges opposite to it close a loop, so their vectors sum to
    zero; at a border vertex the loop is open.
    """
    v = vertices_O
    n = len(v)
    opp = [v[faces[:, (k + 2) % 3]] - v[faces[:, (k + 1) % 3]] for k in range(3)]
    loop = _accumulate(n, faces, opp)
    scale = np.linalg.norm(v[faces[:, 1]] - v[faces[:, 0]], axis=1).mean()
    return np.linalg.norm(loop, axis=1) > 1e-6 * scale


def smooth_over_faces(values: np.ndarray, faces: np.ndarray, iterations: int) -> np.ndarray:
    """Average per-vertex ``values`` through the incident faces ``iterations`` times."""
    n = len(values)
    count = np.maximum(np.bincount(faces.ravel(), minlength=n), 1)
    out = values
    for _ in range(iterations):
        face_mean = out[faces].mean(axis=1)
        acc = np.bincount(faces.ravel(), np.repeat(face_mean, 3), minlength=n)
        out = np.where(count > 0, acc / count, out)
    return out


def mean_curvature(vertices_O: np.ndarray, faces: np.ndarray, normals_O=None,
                   smooth_iterations: int = CURVATURE_SMOOTHING_ITERATIONS) -> np.ndarray:
    """Discrete mean curvature [1/mm] (n,) by the cotangent Laplacian, + where convex.

    Boundary vertices of an open mesh get 0. The sign is taken against ``normals_O`` when given,
    else against the area-weighted face normals.
    """
    v = np.asarray(vertices_O, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = len(v)
    if len(faces) == 0:
        return np.zeros(n)
    e = [v[faces[:, (k + 1) % 3]] - v[faces[:, k]] for k in range(3)]  # edge k -> k+1
    cross = np.cross(e[0], -e[2])
    dbl_area = np.maximum(np.linalg.norm(cross, axis=1), 1e-12)
    contrib = [np.zeros((len(faces), 3)) for _ in range(3)]
    for k in range(3):  # corner k: its cotangent weights the opposite edge (i, j)
        i, j = (k + 1) % 3, (k + 2) % 3
        cot = -np.einsum("ij,ij->i", e[k], e[(k + 2) % 3]) / dbl_area  # a.b / |a x b|
        half = 0.5 * cot[:, None] * e[i]  # e[i] = v_j - v_i
        contrib[i] += half
        contrib[j] -= half
    lap = _accumulate(n, faces, contrib)  # sum_j w_ij (v_j - v_i)
    area = np.bincount(faces.ravel(), np.repeat(dbl_area / 6.0, 3), minlength=n)
    hn = lap / np.maximum(area, 1e-12)[:, None]  # = 2 H n (points into a convex surface)
    if normals_O is None:
        normals = _accumulate(n, faces, [cross, cross, cross])
    else:
        normals = np.asarray(normals_O, dtype=np.float64)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    h = -0.5 * np.einsum("ij,ij->i", hn, normals)
    h[boundary_vertices(v, faces)] = 0.0
    h[area <= 1e-12] = 0.0
    return smooth_over_faces(h, faces, smooth_iterations)


def classify_vertices(vertices_O, faces, weight, signed_distance_mm, monitor_cfg,
                      normals_O=None, reference_curvature=None) -> VertexClasses:
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
    """
    d = np.asarray(signed_distance_mm, dtype=np.float64)
    w = np.asarray(weight, dtype=np.float64)
    dg = float(monitor_cfg.delta_global_mm)
    dl = float(monitor_cfg.delta_local)
    h = mean_curvature(vertices_O, np.asarray(faces, dtype=np.int64), normals_O)
    excess = h if reference_curvature is None else h - np.asarray(reference_curvature, float)
    agree = np.maximum(np.sign(d) * excess, 0.0)  # convex where above, concave where below
    metric = (d / dg) * np.minimum(1.0, agree * LOCAL_CURVATURE_RADIUS_MM)
    code = np.full(d.shape, NORMAL, dtype=np.int8)
    code[metric > dl] = LOCAL_OVERBUILD
    code[metric < -dl] = LOCAL_UNDERBUILD
    code[d > dg] = OVERBUILD
    code[d < -dg] = UNDERBUILD
    code[w < float(monitor_cfg.min_weight)] = UNOBSERVED
    return VertexClasses(code, metric, h)
