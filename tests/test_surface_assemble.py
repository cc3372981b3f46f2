"""Joining chunk meshes (dm2.fusion.surface_assemble): a sphere cut into eight chunk boxes comes
back as one closed surface, each vertex the chunks share kept once, and the merge equals its plain
numpy statement (tests/oracles/first_copies.py) bit for bit."""

import numpy as np
from oracles.first_copies import first_copies

from dm2.core.tolerances import GRID_FRACTION_TOL
from dm2.fusion.surface import mesh_volume
from dm2.fusion.surface_assemble import _first_copies, assemble

VOXEL_MM = 0.5
CHUNK = 32  # voxels per chunk edge; each box has a one-voxel apron on its upper faces
CENTRE = np.array([33.3, 31.8, 32.4])  # [voxels], the sphere straddles all eight chunks
RADIUS = 20.2  # [voxels]


def chunk_parts():
    n = 2 * CHUNK + 1
    g = np.mgrid[0:n, 0:n, 0:n].astype(float)
    d_mm = (np.sqrt(((g - CENTRE[:, None, None, None]) ** 2).sum(0)) - RADIUS) * VOXEL_MM
    d_mm = d_mm.astype(np.float32)
    parts = []
    for o in np.ndindex(2, 2, 2):
        lo = np.array(o) * CHUNK
        box = np.ascontiguousarray(d_mm[lo[0]:lo[0] + CHUNK + 1, lo[1]:lo[1] + CHUNK + 1,
                                        lo[2]:lo[2] + CHUNK + 1])
        parts.append(mesh_volume(box, np.ones_like(box), lo, VOXEL_MM, 1.5, 1.0))
    return parts


def test_a_sphere_over_eight_chunks_is_one_closed_surface_on_its_level():
    parts = chunk_parts()
    assert all(p is not None and p[4].any() for p in parts)  # every chunk has border vertices
    surf = assemble(parts, VOXEL_MM)
    e = np.sort(np.concatenate([surf.faces[:, [0, 1]], surf.faces[:, [1, 2]],
                                surf.faces[:, [2, 0]]]), axis=1)
    _, uses = np.unique(e, axis=0, return_counts=True)
    assert np.all(uses == 2)  # closed: the chunk seams are stitched, no edge left open
    _, copies = np.unique(np.round(surf.vertices_O / (GRID_FRACTION_TOL * VOXEL_MM)), axis=0,
                          return_counts=True)
    assert copies.max() == 1  # each shared vertex kept once
    r = np.linalg.norm(surf.vertices_O / VOXEL_MM - 0.5 - CENTRE, axis=1)
    assert np.abs(r - RADIUS).max() < 0.03
    np.testing.assert_allclose(np.linalg.norm(surf.normals_O, axis=1), 1.0, rtol=1e-12)


def test_the_merge_equals_its_plain_statement():
    parts = chunk_parts()
    verts = np.concatenate([p[0] for p in parts])
    on_border = np.flatnonzero(np.concatenate([p[4] for p in parts]))
    step = GRID_FRACTION_TOL * VOXEL_MM
    ours = _first_copies(verts, on_border, step)
    np.testing.assert_array_equal(ours, first_copies(verts, on_border, step))
    assert np.count_nonzero(ours != np.arange(len(verts))) > 100  # copies were merged
    rng = np.random.default_rng(3)  # random positions, many repeated, some negative
    pts = rng.integers(-40, 40, (5000, 3)) * 0.25 + rng.choice([0.0, 1e-6], (5000, 3))
    border = np.flatnonzero(rng.random(5000) < 0.7)
    np.testing.assert_array_equal(_first_copies(pts, border, step),
                                  first_copies(pts, border, step))
