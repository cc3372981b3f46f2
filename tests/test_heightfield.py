"""HeightField: exact bilinear ray casting, queries, rasterisation and meshing."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from twin.world.heightfield import HeightField


def _plane_field(a=0.1, b=0.05, c=1.0):
    hf = HeightField((40.0, 30.0), 0.25, 6.0)
    x, y = hf.centres_mm()
    gx, gy = np.meshgrid(x, y)
    hf.heights_mm = a * gx + b * gy + c
    return hf


def test_raycast_hits_slope_exactly():
    hf = _plane_field()
    rng = np.random.default_rng(0)
    n = 20000  # large enough for the parallel kernel
    xy = np.column_stack([rng.uniform(1, 39, n), rng.uniform(1, 29, n)])
    p = np.column_stack([xy, 0.1 * xy[:, 0] + 0.05 * xy[:, 1] + 1.0])
    d = rng.normal(size=(n, 3))
    d[:, 2] = -np.abs(d[:, 2]) - 0.3
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t_true = rng.uniform(5, 80, n)
    o = p - d * t_true[:, None]
    t = hf.raycast(o, d)
    assert np.all(np.isfinite(t))
    early = np.abs(t - t_true) >= 1e-6
    # the only other hits allowed: entering the plate's side face under the surface first
    hit = o[early] + d[early] * t[early, None]
    on_side = np.isclose(hit[:, 0], 0) | np.isclose(hit[:, 0], 40) | \
        np.isclose(hit[:, 1], 0) | np.isclose(hit[:, 1], 30)
    assert np.all(on_side) and np.all(t[early] < t_true[early])
    assert np.all(hit[:, 2] <= hf.height_at(hit[:, :2]) + 1e-9)
    assert early.sum() < 5
    # the serial kernel (small batches) agrees with the parallel one
    t_small = hf.raycast(p[:50] - d[:50] * t_true[:50, None], d[:50])
    assert np.max(np.abs(t_small - t_true[:50])) < 1e-6


def test_raycast_hits_step_ramp_walls_and_misses():
    hf = HeightField((20.0, 10.0), 0.5, 4.0)
    x, _ = hf.centres_mm()
    h = np.where(x > 10.0, 2.0, 0.0)  # centres 9.75 -> 0, 10.25 -> 2: a ramp between them
    hf.heights_mm = np.tile(h, (hf.shape[0], 1))
    # horizontal ray at z = 1 travelling +x meets the ramp half way between the centres
    t = hf.raycast([[0.5, 5.0, 1.0]], [[1.0, 0.0, 0.0]])
    assert abs((0.5 + t[0]) - 10.0) < 1e-9
    # vertical rays read the bilinear height exactly, on both sides and on the ramp
    xs = np.array([3.0, 9.75, 9.9, 10.0, 10.25, 17.0])
    o = np.column_stack([xs, np.full(6, 5.0), np.full(6, 50.0)])
    t = hf.raycast(o, np.tile([0.0, 0.0, -1.0], (6, 1)))
    expected = np.interp(xs, [9.75, 10.25], [0.0, 2.0])
    assert np.max(np.abs((50.0 - t) - expected)) < 1e-9
    # the plate's side face: a ray at z = -2 from x < 0 hits x = 0
    t = hf.raycast([[-7.0, 5.0, -2.0]], [[1.0, 0.0, 0.0]])
    assert abs(t[0] - 7.0) < 1e-9
    # off the footprint, under the plate, beyond max range: misses
    o = np.array([[25.0, 5.0, 10.0], [5.0, 5.0, -5.0], [5.0, 5.0, 10.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    assert np.all(np.isinf(hf.raycast(o, d, max_range_mm=np.inf)[:2]))
    assert np.isinf(hf.raycast(o[2:], d[2:], max_range_mm=9.0)[0])
    assert abs(hf.raycast(o[2:], d[2:], max_range_mm=11.0)[0] - 10.0) < 1e-12


def test_raycast_grazing_rays_over_bumps_find_first_hit():
    hf = HeightField((30.0, 30.0), 0.25, 6.0)
    x, y = hf.centres_mm()
    gx, gy = np.meshgrid(x, y)
    hf.heights_mm = 3.0 * np.exp(-((gx - 10) ** 2 + (gy - 15) ** 2) / 4.0) + \
        5.0 * np.exp(-((gx - 20) ** 2 + (gy - 15) ** 2) / 4.0)
    # a ray along +x at z = 2 must stop on the first bump's flank, never on the second
    t = hf.raycast([[0.5, 15.0, 2.0]], [[1.0, 0.0, 0.0]])
    hit_x = 0.5 + t[0]
    assert 7.0 < hit_x < 10.0
    assert abs(hf.height_at([[hit_x, 15.0]])[0] - 2.0) < 1e-9


def test_height_and_normals_on_a_plane():
    hf = _plane_field(0.2, -0.1, 2.0)
    xy = np.array([[5.0, 5.0], [12.3, 20.7], [30.0, 3.3]])
    np.testing.assert_allclose(hf.height_at(xy), 0.2 * xy[:, 0] - 0.1 * xy[:, 1] + 2.0,
                               atol=1e-12)
    n = hf.normals_at(xy)
    expected = np.array([-0.2, 0.1, 1.0]) / np.linalg.norm([-0.2, 0.1, 1.0])
    np.testing.assert_allclose(n, np.tile(expected, (3, 1)), atol=1e-12)
    assert np.isnan(hf.height_at([[-1.0, 5.0]])[0])


def test_heights_are_read_only_and_copy_is_independent():
    hf = HeightField((10.0, 10.0), 0.5)
    with pytest.raises(ValueError):
        hf.heights_mm[0, 0] = 1.0
    with pytest.raises(ValueError, match="expected shape"):
        hf.heights_mm = np.zeros((3, 3))
    with pytest.raises(ValueError, match="multiple of cell_mm"):
        HeightField((10.1, 10.0), 0.25)
    c = hf.copy()
    c.add_heights(np.ones(c.shape))
    assert hf.heights_mm.max() == 0.0 and c.heights_mm.min() == 1.0
    # raised surface is seen by ray casts of the copy only
    assert abs(c.raycast([[5.0, 5.0, 10.0]], [[0.0, 0.0, -1.0]])[0] - 9.0) < 1e-12
    assert abs(hf.raycast([[5.0, 5.0, 10.0]], [[0.0, 0.0, -1.0]])[0] - 10.0) < 1e-12


def test_from_mesh_and_to_mesh_round_trip():
    box = trimesh.creation.box(extents=(10.0, 6.0, 3.0))
    box.apply_translation((20.0, 15.0, 1.5))  # spans x 15..25, y 12..18, z 0..3
    hf = HeightField.from_mesh(box, (40.0, 30.0), 0.5, 6.0)
    x, y = hf.centres_mm()
    gx, gy = np.meshgrid(x, y)
    inside = (np.abs(gx - 20) < 5) & (np.abs(gy - 15) < 3)
    np.testing.assert_allclose(hf.heights_mm[inside], 3.0, atol=1e-5)
    assert np.all(hf.heights_mm[~inside] == 0.0)
    mesh = hf.to_mesh(closed=True)
    assert mesh.is_watertight
    # flat field: the closed mesh is exactly the plate plus constant layer
    flat = HeightField((40.0, 30.0), 0.5, 6.0)
    flat.heights_mm = np.full(flat.shape, 1.5)
    m = flat.to_mesh(closed=True)
    assert m.is_watertight and abs(m.volume - 40 * 30 * 7.5) < 1e-6
    top = flat.to_mesh()
    assert np.allclose(top.bounds, [[0, 0, 1.5], [40, 30, 1.5]])


def test_to_mesh_window_keeps_only_the_requested_cells():
    hf = _plane_field()
    m = hf.to_mesh(window_mm=(10.0, 5.0, 20.0, 12.0))
    assert m.bounds[0, 0] >= 10.0 and m.bounds[1, 0] <= 20.0
    assert m.bounds[0, 1] >= 5.0 and m.bounds[1, 1] <= 12.0
    v = m.vertices
    np.testing.assert_allclose(v[:, 2], 0.1 * v[:, 0] + 0.05 * v[:, 1] + 1.0, atol=1e-12)
    with pytest.raises(ValueError, match="window"):
        hf.to_mesh(window_mm=(10.0, 5.0, 10.1, 5.1))
