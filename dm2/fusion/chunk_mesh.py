"""One chunk's observed surface: marching cubes (:mod:`dm2.fusion.marching_cubes`) of a dense
TSDF box, kept only in the cubes whose eight corners were observed, with the fused weight at
each vertex and a mark on the vertices that lie on the box's faces.

After the marching cubes everything is one compiled pass over the faces and the vertices they
use (:func:`_observed_finish`): the observed-cube test, the renumbering, the weight interpolated
at each vertex and the face mark. The weight is trilinear in the box's weights exactly as
``scipy.ndimage.map_coordinates(w, g.T, order=1, mode="nearest")`` computes it (the same
products in the same order, ``tests/test_marching_cubes.py`` holds the two bit for bit), which
as a call on every chunk took a tenth of the surface's time.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.core.tolerances import GRID_FRACTION_TOL
from dm2.fusion.marching_cubes import marching_cubes

__all__ = ["chunk_surface"]


@njit(cache=True, nogil=True)
def _prepare(d, w, truncation, min_weight):
    """Unobserved voxels (``w <= 0``) to ``truncation`` in place; the observed mask
    ``w >= min_weight``; whether the observed voxels hold both signs."""
    seen = np.empty(d.shape, np.bool_)
    df, wf, sf = d.ravel(), w.ravel(), seen.ravel()
    neg = pos = False
    for i in range(df.size):
        if wf[i] <= 0:
            df[i] = truncation
        sf[i] = wf[i] >= min_weight
        if sf[i]:
            neg |= df[i] < 0
            pos |= df[i] > 0
    return seen, neg and pos


@njit(cache=True, nogil=True)
def _observed_faces(verts, faces, seen, voxel):
    """Faces whose cube (the one holding the triangle's centre) has eight observed corners."""
    n = seen.shape[0] - 1
    keep = np.empty(faces.shape[0], np.bool_)
    three = np.float32(3.0)
    c = np.empty(3, np.int64)
    for j in range(faces.shape[0]):
        for a in range(3):
            s = verts[faces[j, 0], a] + verts[faces[j, 1], a] + verts[faces[j, 2], a]
            c[a] = min(max(np.int64(np.floor(s / three / voxel)), 0), n - 1)
        ok = True
        for k in range(8):
            if not seen[c[0] + (k & 1), c[1] + ((k >> 1) & 1), c[2] + ((k >> 2) & 1)]:
                ok = False
                break
        keep[j] = ok
    return keep


@njit(cache=True, nogil=True)
def _trilinear(w, g, s, idx):
    """``map_coordinates(w, g[:, None], order=1, mode="nearest")`` at one point ``g (3,)``
    float32 inside the box, in float64 and the same order of products and sums; ``s, idx``
    are (3, 2) scratch arrays."""
    for a in range(3):
        cc = np.float64(g[a])
        f = np.floor(cc)
        s[a, 0] = 1.0 - (cc - f)
        s[a, 1] = 1.0 - s[a, 0]
        i0 = np.int64(f)
        last = w.shape[a] - 1
        idx[a, 0] = min(max(i0, 0), last)
        idx[a, 1] = min(max(i0 + 1, 0), last)
    t = 0.0
    for f0 in range(2):
        for f1 in range(2):
            for f2 in range(2):
                coeff = np.float64(w[idx[0, f0], idx[1, f1], idx[2, f2]])
                coeff *= s[0, f0]
                coeff *= s[1, f1]
                coeff *= s[2, f2]
                t += coeff
    return np.float32(t)


@njit(cache=True, nogil=True)
def _observed_finish(verts, faces, normals, seen, w, voxel, tol):
    """The faces of :func:`_observed_faces` and the vertices they use, renumbered in order,
    with each vertex's weight and whether it lies on the box's faces (within ``tol`` voxels):
    ``(verts (k, 3) float32 [mm], faces (f, 3) int64, normals (k, 3) float32, weight (k,)
    float32, on_border (k,) bool)``."""
    keep_f = _observed_faces(verts, faces, seen, voxel)
    used = np.zeros(verts.shape[0], np.bool_)
    nf = 0
    for j in range(faces.shape[0]):
        if keep_f[j]:
            nf += 1
            for a in range(3):
                used[faces[j, a]] = True
    new = np.empty(verts.shape[0], np.int64)
    k = 0
    for i in range(verts.shape[0]):
        new[i] = k
        k += used[i]
    f_out = np.empty((nf, 3), np.int64)
    m = 0
    for j in range(faces.shape[0]):
        if keep_f[j]:
            for a in range(3):
                f_out[m, a] = new[faces[j, a]]
            m += 1
    v_out = np.empty((k, 3), np.float32)
    n_out = np.empty((k, 3), np.float32)
    weight = np.empty(k, np.float32)
    border = np.zeros(k, np.bool_)
    n = np.float32(seen.shape[0] - 1)
    g = np.empty(3, np.float32)
    s = np.empty((3, 2))
    idx = np.empty((3, 2), np.int64)
    for i in range(verts.shape[0]):
        if not used[i]:
            continue
        j = new[i]
        for a in range(3):
            v_out[j, a] = verts[i, a]
            n_out[j, a] = normals[i, a]
            g[a] = verts[i, a] / voxel  # [voxels, box frame]
            if abs(g[a]) < tol or abs(g[a] - n) < tol:
                border[j] = True
        weight[j] = _trilinear(w, g, s, idx)
    return v_out, f_out, n_out, weight, border


def chunk_surface(d: np.ndarray, w: np.ndarray, truncation_mm: float, min_weight: float,
                  voxel_mm: float):
    """The zero level of a chunk's box ``d, w (n+1,)*3`` float32 in the cubes whose eight
    corners have weight ``>= min_weight``: ``(vertices (k, 3) float32 [mm, box frame], faces
    (f, 3) int64, normals (k, 3) float32 pointing into the material, weight (k,) float32
    interpolated in ``w``, on_border (k,) bool: on one of the box's faces)``, or None.

    ``d`` is modified: never-updated voxels (``w <= 0``) read ``truncation_mm`` (free space).
    The cubes visited are skimage's (far corner observed, :func:`marching_cubes`), so that the
    normals sum the same cubes; triangles in cubes with an unobserved corner are then dropped
    with the vertices only they used.
    """
    seen, both_signs = _prepare(d, w, np.float32(truncation_mm), np.float32(min_weight))
    if not both_signs:
        return None
    try:
        verts, faces, normals = marching_cubes(d, seen, voxel_mm)
    except RuntimeError:
        return None  # no zero crossing inside the visited cubes
    out = _observed_finish(verts, faces, normals, seen, np.ascontiguousarray(w, np.float32),
                           np.float32(voxel_mm), np.float32(GRID_FRACTION_TOL))
    return out if len(out[1]) else None
