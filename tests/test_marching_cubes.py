"""The compiled marching cubes of the surface extraction (dm2.fusion.marching_cubes): bit for bit
skimage's Lewiner marching cubes, and, through mesh_volume, a surface on the true zero level
with outward normals, nothing in cubes with an unobserved corner and the weight interpolated
(dm2.fusion.chunk_mesh) bit for bit as scipy's trilinear map_coordinates."""

import numpy as np
import pytest
from scipy.ndimage import map_coordinates
from skimage.measure import marching_cubes as skimage_marching_cubes

from dm2.core.tolerances import GRID_FRACTION_TOL
from dm2.fusion.chunk_mesh import chunk_surface
from dm2.fusion.marching_cubes import marching_cubes
from dm2.fusion.surface import mesh_volume

CENTRE = np.array([16.3, 15.8, 16.1])
RADIUS = 9.7


def sphere(n=33):
    g = np.mgrid[0:n, 0:n, 0:n].astype(float)
    d = np.sqrt(((g - CENTRE[:, None, None, None]) ** 2).sum(0)) - RADIUS
    return d.astype(np.float32), np.ones((n, n, n), np.float32)


def volumes():
    """Noise (every Lewiner case and ambiguity), noisy spheres, spheres quantised to 0.5 so that
    corners sit exactly on the level (degenerate triangles), masks with holes, three spacings."""
    rng = np.random.default_rng(11)
    for k in range(24):
        n = int(rng.integers(6, 22))
        if k % 3 == 0:
            d = rng.normal(size=(n, n + 1, n + 2)).astype(np.float32)
        else:
            g = np.mgrid[0:n, 0:n + 1, 0:n + 2].astype(float)
            c = rng.uniform(2, n - 2, 3)
            d = np.sqrt(((g - c[:, None, None, None]) ** 2).sum(0)) - rng.uniform(1, n / 2)
            d = (d + rng.normal(0, 0.3, d.shape)).astype(np.float32)
            if k % 3 == 2:
                d = np.round(d * 2) / 2
        mask = rng.random(d.shape) > (0.2 if k % 2 else 0.0)
        yield d, mask, float(rng.choice([1.0, 0.5, 0.4]))


def test_bit_for_bit_skimages_lewiner_marching_cubes():
    n_cases = 0
    for d, mask, spacing in volumes():
        theirs = skimage_marching_cubes(d, 0.0, spacing=(spacing,) * 3, mask=mask,
                                        gradient_direction="descent", allow_degenerate=False)
        ours = marching_cubes(d, mask, spacing)
        for a, b in zip(theirs[:3], ours, strict=True):
            assert a.shape == b.shape
            np.testing.assert_array_equal(a, b)
        n_cases += 1
    assert n_cases == 24


def test_no_level_in_the_visited_cubes_raises_like_skimage():
    d = np.ones((5, 5, 5), np.float32)
    d[0, 0, 0] = -1.0
    mask = np.zeros_like(d, dtype=bool)  # no cube visited
    with pytest.raises(RuntimeError):
        marching_cubes(d, mask, 0.5)


def test_sphere_on_its_level_normals_outward_and_closed():
    d, w = sphere()
    v, f, wv, nrm, border = mesh_volume(d, w, np.zeros(3, np.int64), 0.5, 1.5, 1.0)
    r = np.linalg.norm(v / 0.5 - 0.5 - CENTRE, axis=1)  # vertices_O: voxel centres at i + 0.5
    assert np.abs(r - RADIUS).max() < 0.03
    radial = (v / 0.5 - 0.5 - CENTRE) / r[:, None]
    assert np.sum(nrm * radial, axis=1).min() > 0.99
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, uses = np.unique(e, axis=0, return_counts=True)
    assert np.all(uses == 2)  # closed: every edge between exactly two triangles
    normal_f = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert np.all(np.sum(normal_f * (v[f[:, 0]] / 0.5 - 0.5 - CENTRE), axis=1) > 0)  # outward
    np.testing.assert_array_equal(wv, 1.0)
    assert not border.any()


def test_unobserved_corners_leave_their_cubes_open_and_weight_is_interpolated():
    d, w = sphere()
    w[20:] = 0.5  # below min_weight from x = 20 on: cubes reaching x >= 20 are not meshed
    w[:8] = 3.0
    v, f, normals = chunk_surface(d.copy(), w, 1.5, 1.0, 1.0)[:3]
    assert v[:, 0].max() <= 19.0 and len(f) > 100
    full = chunk_surface(*sphere(), 1.5, 1.0, 1.0)[0]
    assert np.count_nonzero(full[:, 0] <= 19.0) == len(v)  # the same surface up to x = 19
    _, _, wv, _, _ = mesh_volume(d.copy(), w, np.zeros(3, np.int64), 1.0, 1.5, 1.0)
    low = v[:, 0] < 7
    np.testing.assert_allclose(wv[low], 3.0)
    between = (v[:, 0] > 7) & (v[:, 0] < 8)  # on x edges from weight 3 to weight 1
    np.testing.assert_allclose(wv[between], 3.0 - 2.0 * (v[between, 0] - 7.0), rtol=1e-6)


def test_never_updated_voxels_read_as_free_space():
    d, w = sphere()
    w[:, :, :12] = 0.0  # never updated: whatever d holds there is replaced by the truncation
    d[:, :, :12] = -5.0
    v = chunk_surface(d, w, 1.5, 1.0, 1.0)[0]
    assert np.all(d[:, :, :12] == np.float32(1.5))
    assert v[:, 2].min() >= 12.0


def test_a_corner_exactly_on_the_level_makes_no_zero_area_triangle():
    d, w = sphere()
    d[16, 16, 26] = 0.0  # the sphere's top passes through a grid point
    v, f = chunk_surface(d, w, 1.5, 1.0, 1.0)[:2]
    area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    assert area.min() > 0


def test_vertex_weight_and_box_faces_equal_scipys_trilinear_interpolation_bit_for_bit():
    rng = np.random.default_rng(5)
    n_checked = n_border = 0
    for d, _, spacing in volumes():
        w = rng.uniform(0.0, 30.0, d.shape).astype(np.float32)
        w[rng.random(d.shape) < 0.1] = 0.0
        d = d[:, : d.shape[0], : d.shape[0]]  # a cube, as a chunk's box is
        w = np.ascontiguousarray(w[:, : d.shape[0], : d.shape[0]])
        out = chunk_surface(d.copy(), w, 1.5, 0.0, spacing)
        if out is None:
            continue
        v, f, nrm, wv, border = out
        g = v / spacing  # float32, as the vertices are
        expected = map_coordinates(w, g.T, order=1, mode="nearest").astype(np.float32)
        np.testing.assert_array_equal(wv.view(np.uint32), expected.view(np.uint32))
        n = d.shape[0] - 1
        np.testing.assert_array_equal(
            border, np.any((np.abs(g) < GRID_FRACTION_TOL) | (np.abs(g - n) < GRID_FRACTION_TOL),
                           axis=1))
        n_checked += 1
        n_border += int(border.sum())
    assert n_checked >= 20 and n_border > 100
