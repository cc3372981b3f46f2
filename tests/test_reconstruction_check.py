"""The reconstruction check's distance to the twin's true surface (dm2.bench.reconstruction)."""

from types import SimpleNamespace

import numpy as np
import open3d as o3d
import pytest

from dm2.bench.reconstruction import (
    grid_mesh_distance,
    grid_of_mesh,
    mesh_distance,
    truth_checks,
)
from dm2.defects.classify import CLASS_NAMES
from twin.world.heightfield import HeightField
from twin.world.truth import write_layer_surface


def _tower_field(rough_mm=0.05, seed=3):
    """A 30 x 20 mm block 12 mm tall on a 60 mm plate, with a rough top (the twin's grid)."""
    rng = np.random.default_rng(seed)
    hf = HeightField(size_mm=(60.0, 60.0), cell_mm=0.25, thickness_mm=5.0)
    x, y = hf.centres_mm()
    block = (x[None, :] > 15) & (x[None, :] < 45) & (y[:, None] > 20) & (y[:, None] < 40)
    hf._h[:] = np.where(block, 12.0 + rng.normal(0.0, rough_mm, block.shape), 0.0)
    return hf


def _open3d_distance(points, vertices, faces):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)),
                        o3d.core.Tensor(faces.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def test_twin_truth_mesh_is_read_as_its_grid(tmp_path):
    hf = _tower_field()
    mesh = hf.to_mesh(window_mm=(10.0, 15.0, 50.0, 45.0))
    grid = grid_of_mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    h, x0, y0, cell = grid
    assert cell == pytest.approx(0.25) and (x0, y0) == pytest.approx((10.125, 15.125))
    x, y = hf.centres_mm()
    ci, cj = np.flatnonzero((x >= 10) & (x <= 50)), np.flatnonzero((y >= 15) & (y <= 45))
    np.testing.assert_array_equal(h, hf.heights_mm[cj[0]:cj[-1] + 1, ci[0]:ci[-1] + 1])
    faces = np.asarray(mesh.faces)
    assert grid_of_mesh(np.asarray(mesh.vertices), faces[::-1]) is None  # other face order
    assert grid_of_mesh(np.asarray(mesh.vertices), faces[:, [0, 2, 1]]) is None  # other split
    shuffled = np.asarray(mesh.vertices)[np.random.default_rng(0).permutation(len(faces) // 2)]
    assert grid_of_mesh(shuffled, faces[: len(faces) // 4]) is None


def test_grid_distance_is_exact():
    hf = _tower_field()
    mesh = hf.to_mesh(window_mm=(5.0, 5.0, 55.0, 55.0))
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    grid = grid_of_mesh(v, f)
    # analytic: above the bare plate, beside the block's wall, far inside the block
    probes = np.array([[8.0, 8.0, 3.0],      # 3 mm above the plate, far from the block
                       [14.0, 30.0, 6.0],    # 1 mm in front of the wall x = 15 mm (+- a cell)
                       [30.0, 30.0, 4.0]])   # inside the block, 5 mm from the wall y = 20+
    d = grid_mesh_distance(probes, *grid)
    assert d[0] == pytest.approx(3.0, abs=1e-9)
    assert 0.95 <= d[1] <= 1.01  # the wall: 12 mm over one cell, from x = 14.875 to 15.125
    assert d[2] == pytest.approx(np.min(_open3d_distance(probes[2:], v, f)), abs=1e-4)
    # against Open3D's BVH on points near and far from the surface, wall and top included
    rng = np.random.default_rng(7)
    near = v[::5] + rng.normal(0.0, 0.3, v[::5].shape)
    far = rng.uniform(v.min(axis=0), v.max(axis=0), (3000, 3))
    points = np.concatenate([near, far])
    np.testing.assert_allclose(grid_mesh_distance(points, *grid),
                               _open3d_distance(points, v, f), atol=2e-5)


def test_other_meshes_go_through_open3d():
    v = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]])
    f = np.array([[0, 1, 2]])
    assert grid_of_mesh(v, f) is None
    d = mesh_distance(np.array([[1.0, 1.0, 2.0], [20.0, 0.0, 0.0]]), v, f)
    np.testing.assert_allclose(d, [2.0, 10.0], atol=1e-5)


def test_reconstruction_errors_per_layer(tmp_path):
    """A reconstruction 0.2 mm above the truth everywhere reads RMS = p95 = 0.2 mm; vertices
    the profilers never saw and those at the cropped border are not compared."""
    hf = _tower_field(rough_mm=0.0)
    write_layer_surface(hf, tmp_path / "layer_004.ply")
    x, y = hf.centres_mm()
    gx, gy = np.meshgrid(x[20:220:3], y[20:220:3])  # the block's top and the plate around
    top = np.column_stack([gx.ravel(), gy.ravel(), hf.heights_mm[20:220:3, 20:220:3].ravel()])
    inside = ((np.abs(top[:, 0] - 30.0) < 14.0) & (np.abs(top[:, 1] - 30.0) < 9.0)
              | (np.abs(top[:, 0] - 30.0) > 16.0) | (np.abs(top[:, 1] - 30.0) > 11.0))
    top = top[inside]  # a cell off the walls, both sides
    lo, hi = np.array([5.0, 10.0]) + 1.0, np.array([55.0, 50.0]) - 1.0  # truth: block + 10 mm
    top = top[np.all((top[:, :2] > lo + 0.3) & (top[:, :2] < hi - 0.3), axis=1)]
    top[:, 2] += 0.2
    seen = CLASS_NAMES.index("normal")
    unseen = CLASS_NAMES.index("unobserved")
    stray = np.array([[30.0, 30.0, 40.0]])  # 28 mm above the top, but never observed
    vertices = np.concatenate([top, stray])
    codes = np.concatenate([np.full(len(top), seen), [unseen]])
    result = SimpleNamespace(layer=4, deviation=SimpleNamespace(vertices_O=vertices,
                                                                class_code=codes),
                             regions=[], track_ids=[])
    border = SimpleNamespace(layer=4, deviation=SimpleNamespace(  # inside the crop margin
        vertices_O=np.array([[5.5, 30.0, 0.2]]), class_code=np.array([seen])),
        regions=[], track_ids=[])
    assert truth_checks([border], tmp_path) == ({}, {})
    missing = SimpleNamespace(layer=5, deviation=result.deviation, regions=[],
                              track_ids=[])  # no truth written
    out, _ = truth_checks([result, missing], tmp_path)
    assert set(out) == {4}
    assert out[4]["n_vertices"] == len(top)
    assert out[4]["rms_mm"] == pytest.approx(0.2, abs=1e-6)
    assert out[4]["p95_mm"] == pytest.approx(0.2, abs=1e-6)


def test_track_truth_tells_the_part_from_the_measurement(tmp_path):
    """Two tracks on the block's top, both 0.8 mm under the reference: one whose vertices lie
    on the true surface (the part itself stands off the reference: part_deviates) and one whose
    vertices lie 0.6 mm under it (the measurement is off); a region with no track and a layer
    without truth are not counted."""
    hf = _tower_field(rough_mm=0.0)
    write_layer_surface(hf, tmp_path / "layer_002.ply")
    rng = np.random.default_rng(5)
    on_part = np.column_stack([rng.uniform(20, 28, 40), rng.uniform(25, 35, 40), np.full(40, 12.0)])
    off_part = np.column_stack([rng.uniform(32, 40, 30), rng.uniform(25, 35, 30),
                                np.full(30, 11.4)])
    untracked = np.array([[30.0, 22.0, 12.0]])
    vertices = np.concatenate([on_part, off_part, untracked])
    signed = np.full(len(vertices), -0.8)
    regions = [SimpleNamespace(vertex_ids=np.arange(40)),
               SimpleNamespace(vertex_ids=np.arange(40, 70)),
               SimpleNamespace(vertex_ids=np.array([70]))]
    codes = np.full(len(vertices), CLASS_NAMES.index("underbuild"))
    dev = SimpleNamespace(vertices_O=vertices, signed_distance_mm=signed, class_code=codes)
    result = SimpleNamespace(layer=2, deviation=dev, regions=regions, track_ids=[7, 9, None])
    no_truth = SimpleNamespace(layer=3, deviation=dev, regions=regions, track_ids=[7, 9, None])
    _, out = truth_checks([result, no_truth], tmp_path)
    assert set(out) == {7, 9}
    assert out[7]["n_vertices"] == 40 and out[9]["n_vertices"] == 30
    assert out[7]["deviation_median_mm"] == pytest.approx(-0.8)
    assert out[7]["truth_distance_median_mm"] == pytest.approx(0.0, abs=1e-9)
    assert out[7]["part_deviates"] is True
    assert out[9]["truth_distance_median_mm"] == pytest.approx(0.6, abs=1e-9)
    assert out[9]["truth_distance_p90_mm"] == pytest.approx(0.6, abs=1e-9)
    assert out[9]["part_deviates"] is False
