"""Joining chunk meshes into one surface: vertices that neighbouring chunks share on their
faces are merged, triangles that the merge made degenerate dropped, normals renormalised.

Runs over the whole surface at every update (the chunk meshes are cached, their union is not),
so it is kept to a few passes: only the vertices on chunk faces are grouped (a hash table of
their rounded positions; each copy maps to its first copy, the lowest-numbered), and the
renumbering, the face remap and the normalisation are one compiled pass.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.core.tolerances import DIVISOR_FLOOR, GRID_FRACTION_TOL
from dm2.fusion.surface_mesh import SurfaceMesh


@njit(cache=True, nogil=True, error_model="numpy")
def _compact(target, verts, faces, weight, normals, floor):
    """Keep vertex i where ``target[i] == i`` (a first copy), renumber, remap the faces through
    ``target`` and drop the degenerate ones; normals divided by ``max(|n|, floor)`` (``floor``
    > 0). The faces returned are the first rows of a buffer as long as ``faces``."""
    n = target.shape[0]
    new = np.empty(n, np.int64)
    k = 0
    for i in range(n):
        if target[i] == i:
            new[i] = k
            k += 1
    for i in range(n):  # a later copy takes the number of its first copy (a kept vertex)
        if target[i] != i:
            new[i] = new[target[i]]
    v_out = np.empty((k, 3))
    w_out = np.empty(k, np.float32)
    n_out = np.empty((k, 3))
    for i in range(n):
        if target[i] == i:
            j = new[i]
            v_out[j, 0], v_out[j, 1], v_out[j, 2] = verts[i, 0], verts[i, 1], verts[i, 2]
            w_out[j] = weight[i]
            x, y, z = normals[i, 0], normals[i, 1], normals[i, 2]
            s = max(np.sqrt(x * x + y * y + z * z), floor)
            n_out[j, 0], n_out[j, 1], n_out[j, 2] = x / s, y / s, z / s
    f_out = np.empty_like(faces)
    m = 0
    for t in range(faces.shape[0]):
        a, b, c = new[faces[t, 0]], new[faces[t, 1]], new[faces[t, 2]]
        if a != b and b != c and a != c:
            f_out[m, 0], f_out[m, 1], f_out[m, 2] = a, b, c
            m += 1
    return v_out, f_out[:m], w_out, n_out


@njit(cache=True, nogil=True)
def _first_copies(verts, on_border, step):
    """``target (n,)``: each vertex's first copy, the lowest-numbered vertex of ``on_border``
    (increasing indices) at the same position rounded to ``step`` [mm]; itself for the rest.
    An open-addressing table of the rounded positions (``np.rint``, as ``np.round``)."""
    n = verts.shape[0]
    target = np.arange(n)
    m = on_border.shape[0]
    size = 16
    while size < 2 * m:
        size *= 2
    mask = size - 1
    keys = np.empty((size, 3), np.int64)
    first = np.full(size, -1, np.int64)
    for k in range(m):
        i = on_border[k]
        kx = np.int64(np.rint(verts[i, 0] / step))
        ky = np.int64(np.rint(verts[i, 1] / step))
        kz = np.int64(np.rint(verts[i, 2] / step))
        h = ((kx * 73856093) ^ (ky * 19349663) ^ (kz * 83492791)) & mask
        while first[h] >= 0:
            if keys[h, 0] == kx and keys[h, 1] == ky and keys[h, 2] == kz:
                target[i] = first[h]
                break
            h = (h + 1) & mask
        else:
            keys[h, 0], keys[h, 1], keys[h, 2] = kx, ky, kz
            first[h] = i
    return target


def assemble(parts: list, voxel_mm: float) -> SurfaceMesh:
    """Join chunk mesh tuples (None entries skipped; see :func:`dm2.fusion.surface.mesh_volume`)
    into one surface, merging the vertices chunks share on their faces."""
    parts = [m for m in parts if m is not None]
    if not parts:
        return SurfaceMesh.empty()
    offs = np.cumsum([0] + [len(p[0]) for p in parts])
    verts = np.concatenate([p[0] for p in parts])
    faces = np.concatenate([p[1] + o for p, o in zip(parts, offs[:-1], strict=True)])
    weight = np.concatenate([p[2] for p in parts])
    normals = np.concatenate([p[3] for p in parts])
    on_border = np.flatnonzero(np.concatenate([p[4] for p in parts]))
    target = _first_copies(verts, on_border, GRID_FRACTION_TOL * voxel_mm)
    v, f, w, nrm = _compact(target, verts, faces, weight, normals, DIVISOR_FLOOR)
    return SurfaceMesh(v, f, w, nrm)
