"""The marching-cubes kernel of the surface extraction (dm2.fusion.marching_cubes): the zero
level set's vertices where skimage puts them, a closed and consistently wound surface, normals
along the true gradient, and nothing in cubes with an unobserved corner."""

import numpy as np
from skimage.measure import marching_cubes as skimage_marching_cubes

from dm2.fusion.marching_cubes import TABLE, marching_cubes

CENTRE = np.array([16.3, 15.8, 16.1])
RADIUS = 9.7


def sphere(n=33):
    g = np.mgrid[0:n, 0:n, 0:n].astype(float)
    d = np.sqrt(((g - CENTRE[:, None, None, None]) ** 2).sum(0)) - RADIUS
    return d.astype(np.float32), np.ones((n, n, n), np.float32)


def edge_use(faces):
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)


def test_sphere_vertices_are_skimages_and_the_surface_is_closed_and_outward():
    d, w = sphere()
    v, f, wv, nrm = marching_cubes(d, w, 1.0)
    sv, sf, _, _ = skimage_marching_cubes(d, 0.0)
    assert len(v) == len(sv) and len(f) == len(sf)
    ours = v[np.lexsort(v.T)]
    theirs = sv[np.lexsort(sv.T)].astype(np.float64)
    np.testing.assert_allclose(ours, theirs, atol=1e-5)
    r = np.linalg.norm(v - CENTRE, axis=1)
    assert np.abs(r - RADIUS).max() < 0.03  # linear interpolation of a sphere's distance
    _, uses = edge_use(f)
    assert np.all(uses == 2)  # closed: every edge between exactly two triangles
    normal_f = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert np.all(np.sum(normal_f * (v[f[:, 0]] - CENTRE), axis=1) > 0)  # wound outward
    radial = (v - CENTRE) / r[:, None]
    assert np.sum(nrm * radial, axis=1).min() > 0.995
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-9)
    np.testing.assert_array_equal(wv, 1.0)


def test_noise_is_closed_inside_the_box_whatever_the_ambiguous_faces():
    rng = np.random.default_rng(7)
    d = rng.normal(size=(17, 17, 17)).astype(np.float32)
    v, f, _, _ = marching_cubes(d, np.ones_like(d), 1.0)
    assert len(f) > 1000
    edges, uses = edge_use(f)
    open_edges = edges[uses == 1]
    on_box = np.any((v[open_edges[:, 0]] % 16 == 0) & (v[open_edges[:, 1]] % 16 == 0), axis=1)
    assert on_box.all()  # open only where the box ends
    assert (TABLE[:, :, 0] <= (TABLE.shape[2] - 1) // 3).all()


def test_unobserved_corners_leave_their_cubes_open_and_weight_is_interpolated():
    d, w = sphere()
    w[20:] = 0.5  # below min_weight from x = 20 on: cubes reaching x >= 20 are not meshed
    w[:8] = 3.0
    v, f, wv, _ = marching_cubes(d, w, 1.0)
    assert v[:, 0].max() <= 19.0 and len(f) > 100
    full, _, _, _ = marching_cubes(*sphere(), 1.0)
    assert np.count_nonzero(full[:, 0] <= 19.0) >= len(v)
    low = v[:, 0] < 7
    np.testing.assert_allclose(wv[low], 3.0)
    between = (v[:, 0] > 7) & (v[:, 0] < 8)  # on x edges from weight 3 to weight 1
    np.testing.assert_allclose(wv[between], 3.0 - 2.0 * (v[between, 0] - 7.0), rtol=1e-6)


def test_a_corner_exactly_on_the_level_makes_no_zero_area_triangle():
    d, w = sphere()
    d[16, 16, 26] = 0.0  # the sphere's top passes through a grid point
    v, f, _, _ = marching_cubes(d, w, 1.0)
    area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    assert area.min() > 0
