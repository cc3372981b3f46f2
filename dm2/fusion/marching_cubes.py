"""Marching cubes of one dense TSDF box: scikit-image's Lewiner marching cubes, compiled with
numba and without the GIL, bit for bit the same vertices, triangles and normals.

Why not call ``skimage.measure.marching_cubes``: the surface is extracted every layer from every
touched chunk, and skimage's call with our cube filter, per-vertex weight and normals around it
took most of the surface's time, three times Open3D's extraction of the same stream
(``benchmarks/fusion.py``). Why not another algorithm: the monitor's uncertainty and its
real-time alarms read the surface's vertices and normals, and a surface that differs by a
degree here and there moves calls near their thresholds; this one changes only the time.

What skimage computes, and so this module (``tests/test_marching_cubes.py`` holds the two
equal on noisy and masked volumes):

* a cube is visited only where ``mask`` is set at its far corner ``(z+1, y+1, x+1)``;
* the case and its ambiguities are resolved with Lewiner's tables (read from skimage's own
  table module: :mod:`dm2.fusion.marching_cubes_luts`) and its face and interior tests
  (:mod:`dm2.fusion.marching_cubes_cases`);
* a vertex per cut edge at the linear zero crossing (weights ``1 / (eps + |v|)``), shared by the
  cubes around the edge; a centre vertex where a tiling needs one;
* the normal sums, for every triangle that uses the vertex, the cube's one-sided differences at
  the edge's two corners weighted like the position, in float32, then normalised. skimage's
  quirk is kept on purpose: the gradients of corners 2/3 and 6/7 are read swapped;
* ``descent`` orientation (each triangle's order reversed), vertices scaled by the spacing, and
  degenerate triangles removed with their vertices merged (``allow_degenerate=False``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.fusion import marching_cubes_luts as L
from dm2.fusion.marching_cubes_cases import FLT_EPSILON, get, tiling


@njit(cache=True, nogil=True)
def _corner_gradients(v, vg):
    """skimage's per-corner gradients ``vg[8, 3]`` (its storage order, see the module doc)."""
    vg[0, 0], vg[0, 1], vg[0, 2] = v[0] - v[1], v[0] - v[3], v[0] - v[4]
    vg[1, 0], vg[1, 1], vg[1, 2] = v[0] - v[1], v[1] - v[2], v[1] - v[5]
    vg[2, 0], vg[2, 1], vg[2, 2] = v[3] - v[2], v[1] - v[2], v[2] - v[6]
    vg[3, 0], vg[3, 1], vg[3, 2] = v[3] - v[2], v[0] - v[3], v[3] - v[7]
    vg[4, 0], vg[4, 1], vg[4, 2] = v[4] - v[5], v[4] - v[7], v[0] - v[4]
    vg[5, 0], vg[5, 1], vg[5, 2] = v[4] - v[5], v[5] - v[6], v[1] - v[5]
    vg[6, 0], vg[6, 1], vg[6, 2] = v[7] - v[6], v[5] - v[6], v[2] - v[6]
    vg[7, 0], vg[7, 1], vg[7, 2] = v[7] - v[6], v[4] - v[7], v[3] - v[7]


@njit(cache=True, nogil=True)
def _centre(v, vg, x, y, z, out):
    """The centre vertex ``out[0:3]`` and its gradient ``out[3:6]`` (skimage's)."""
    s = np.empty(8)
    for k in range(8):
        s[k] = 1.0 / (FLT_EPSILON + abs(v[k]))
    # corner k of skimage's numbering sits at (x, y, z) offsets
    ox = (0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0)
    oy = (0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0)
    oz = (0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0)
    fx = fy = fz = ff = 0.0
    for k in range(8):
        fx += ox[k] * s[k]
        fy += oy[k] * s[k]
        fz += oz[k] * s[k]
        ff += s[k]
    out[0], out[1], out[2] = x + 1.0 * fx / ff, y + 1.0 * fy / ff, z + 1.0 * fz / ff
    gx = gy = gz = 0.0
    for k in range(8):
        gx += s[k] * vg[k, 0]
        gy += s[k] * vg[k, 1]
        gz += s[k] * vg[k, 2]
    out[3], out[4], out[5] = gx, gy, gz


@njit(cache=True, nogil=True)
def _lewiner(im, mask):
    """skimage's ``_marching_cubes_lewiner_cy.marching_cubes(im, 0.0, luts, 1, 0, mask)``:
    ``(vertices (k, 3) float32 [x, y, z], faces (f, 3) int64, normals (k, 3) float32)``."""
    nz, ny, nx = im.shape
    slot = np.full((nz, ny, nx, 4), -1, np.int32)
    verts = np.empty((1024, 3), np.float32)
    nrm = np.zeros((1024, 3), np.float32)
    faces = np.empty(3072, np.int64)
    nv = nf = 0
    v = np.empty(8)
    vv = np.empty(8)
    vg = np.empty((8, 3))
    c12 = np.empty(6)
    for z in range(nz - 1):
        for y in range(ny - 1):
            for x in range(nx - 1):
                if not mask[z + 1, y + 1, x + 1]:
                    continue
                v[0], v[1] = im[z, y, x], im[z, y, x + 1]
                v[2], v[3] = im[z, y + 1, x + 1], im[z, y + 1, x]
                v[4], v[5] = im[z + 1, y, x], im[z + 1, y, x + 1]
                v[6], v[7] = im[z + 1, y + 1, x + 1], im[z + 1, y + 1, x]
                index = 0
                for k in range(8):
                    if v[k] > 0.0:
                        index += 1 << k
                case = get(L.T_CASES, index, 0, 0)
                if case <= 0:
                    continue
                config = get(L.T_CASES, index, 1, 0)
                t, sub, ntri = tiling(v, case, config)
                vv[0], vv[1], vv[2], vv[3] = v[0], v[1], v[3], v[2]
                vv[4], vv[5], vv[6], vv[7] = v[4], v[5], v[7], v[6]
                _corner_gradients(v, vg)
                centre_done = False
                for i in range(3 * ntri):
                    vi = get(t, config, i, 0) if sub < 0 else get(t, config, sub, i)
                    # the vertex's slot: edges by their low corner and direction, the centre
                    # vertex by its cube
                    if vi == 12:
                        key = (z, y, x, 3)
                    elif vi < 8:
                        zl = z if vi < 4 else z + 1
                        e = vi % 4
                        key = (zl, y + (e == 2), x + (e == 1), 1 if e == 1 or e == 3 else 0)
                    else:
                        key = (z, y + (vi == 10 or vi == 11), x + (vi == 9 or vi == 10), 2)
                    iv = slot[key]
                    if nv == verts.shape[0] and iv < 0:
                        verts = _grow(verts)
                        nrm = _grow(nrm)
                    if nf == faces.shape[0]:
                        faces = _grow1(faces)
                    if vi == 12:
                        if not centre_done:
                            _centre(v, vg, x, y, z, c12)
                            centre_done = True
                        if iv < 0:
                            iv = nv
                            verts[nv, 0], verts[nv, 1], verts[nv, 2] = c12[0], c12[1], c12[2]
                            nv += 1
                            slot[key] = iv
                        faces[nf] = iv
                        nf += 1
                        for a in range(3):
                            nrm[iv, a] += np.float32(c12[3 + a])
                        continue
                    dx1, dx2 = L.EDGE_REL[0, vi, 0], L.EDGE_REL[0, vi, 1]
                    dy1, dy2 = L.EDGE_REL[1, vi, 0], L.EDGE_REL[1, vi, 1]
                    dz1, dz2 = L.EDGE_REL[2, vi, 0], L.EDGE_REL[2, vi, 1]
                    i1 = dz1 * 4 + dy1 * 2 + dx1
                    i2 = dz2 * 4 + dy2 * 2 + dx2
                    s1 = 1.0 / (FLT_EPSILON + abs(vv[i1]))
                    s2 = 1.0 / (FLT_EPSILON + abs(vv[i2]))
                    if iv < 0:
                        ff = s1 + s2
                        fx = dx1 * s1 + dx2 * s2
                        fy = dy1 * s1 + dy2 * s2
                        fz = dz1 * s1 + dz2 * s2
                        iv = nv
                        verts[nv, 0] = x + 1.0 * fx / ff
                        verts[nv, 1] = y + 1.0 * fy / ff
                        verts[nv, 2] = z + 1.0 * fz / ff
                        nv += 1
                        slot[key] = iv
                    faces[nf] = iv
                    nf += 1
                    f1, f2 = np.float64(np.float32(s1)), np.float64(np.float32(s2))
                    for a in range(3):
                        nrm[iv, a] += np.float32(vg[i1, a] * f1)
                    for a in range(3):
                        nrm[iv, a] += np.float32(vg[i2, a] * f2)
    normals = np.empty((nv, 3), np.float32)
    for i in range(nv):
        ln = 0.0
        for a in range(3):
            ln += np.float64(nrm[i, a]) * np.float64(nrm[i, a])
        if ln > 0.0:
            ln = 1.0 / ln ** 0.5
        for a in range(3):
            normals[i, a] = nrm[i, a] * ln
    return verts[:nv].copy(), faces[:nf].copy().reshape(-1, 3), normals


@njit(cache=True, nogil=True)
def _grow(a):
    out = np.zeros((2 * a.shape[0], a.shape[1]), a.dtype)
    out[: a.shape[0]] = a
    return out


@njit(cache=True, nogil=True)
def _grow1(a):
    out = np.empty(2 * a.shape[0], a.dtype)
    out[: a.shape[0]] = a
    return out


@njit(cache=True, nogil=True)
def _degenerate(vertices, faces):
    """skimage's ``remove_degenerate_faces``: faces with two vertices at one position are
    dropped and those vertices merged into the lower index. Returns (vertex keep mask, faces)."""
    k = vertices.shape[0]
    vmap = np.arange(k)
    face_ok = np.ones(faces.shape[0], np.bool_)
    for j in range(faces.shape[0]):
        for a, b in ((0, 1), (0, 2), (1, 2)):
            ia, ib = faces[j, a], faces[j, b]
            if vertices[ia, 0] == vertices[ib, 0] and vertices[ia, 1] == vertices[ib, 1] \
                    and vertices[ia, 2] == vertices[ib, 2]:
                m = min(vmap[ia], vmap[ib])
                vmap[ia] = m
                vmap[ib] = m
                face_ok[j] = False
    keep = np.empty(k, np.bool_)
    new = np.empty(k, np.int64)
    at = -1
    for i in range(k):
        keep[i] = vmap[i] == i
        at += keep[i]
        new[i] = at
    out = np.empty((face_ok.sum(), 3), np.int64)
    n = 0
    for j in range(faces.shape[0]):
        if face_ok[j]:
            for a in range(3):
                out[n, a] = new[vmap[faces[j, a]]]
            n += 1
    return keep, out


def marching_cubes(volume: np.ndarray, mask: np.ndarray, spacing_mm: float):
    """``skimage.measure.marching_cubes(volume, 0.0, spacing=(spacing_mm,) * 3,
    gradient_direction="descent", mask=mask, allow_degenerate=False)[:3]``, bit for bit:
    ``(vertices (k, 3) float32 [mm], faces (f, 3) int64, normals (k, 3) float32 unit)``.

    Raises RuntimeError (as skimage does) when no cube holds the zero level.
    """
    verts, faces, normals = _lewiner(np.ascontiguousarray(volume, np.float32),
                                     np.ascontiguousarray(mask, np.bool_))
    if not len(verts):
        raise RuntimeError("No surface found at the given iso value.")
    return _skimage_output(verts, faces, normals, np.float64(spacing_mm))


@njit(cache=True, nogil=True)
def _skimage_output(verts, faces, normals, spacing):
    """skimage's finishing of the kernel's output: axes to (z, y, x), vertices times the
    spacing (float64, back to float32), each triangle reversed (descent), degenerate ones out."""
    k = verts.shape[0]
    v = np.empty((k, 3), np.float32)
    for i in range(k):
        for a in range(3):
            v[i, a] = np.float32(np.float64(verts[i, 2 - a]) * spacing)
    f = np.empty_like(faces)
    for j in range(faces.shape[0]):
        f[j, 0], f[j, 1], f[j, 2] = faces[j, 2], faces[j, 1], faces[j, 0]
    keep, f = _degenerate(v, f)
    return v[keep], f, np.ascontiguousarray(normals[keep][:, ::-1])
