"""Surface extraction: position, orientation, chunk seams, incremental updates, PLY output."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.core.messages import MessageError
from dm2.fusion.surface import SurfaceExtractor, SurfaceMesh, read_ply
from dm2.fusion.tsdf.field import SparseTSDF


def _fused_plane(z=0.3, extent=40.0, seed=0, tsdf=None):
    rng = np.random.default_rng(seed)
    n = 150_000
    pts = np.column_stack([rng.uniform(0, extent, n), rng.uniform(0, extent, n), np.full(n, z)])
    tsdf = tsdf or SparseTSDF(0.5, 1.5)
    tsdf.integrate(pts + [0.0, -50.0, 80.0], pts)
    return tsdf


def test_plane_surface_position_orientation_and_area():
    tsdf = _fused_plane(z=0.3)
    surf = SurfaceExtractor(tsdf, min_weight=1.0).update()
    err = np.abs(surf.vertices_O[:, 2] - 0.3)
    assert np.median(err) < 0.02 and np.percentile(err, 99) < 0.08 and err.max() < 0.12
    assert np.mean(surf.normals_O[:, 2] > 0.95) > 0.98 and np.all(surf.normals_O[:, 2] > 0.5)
    tm = surf.to_trimesh()
    assert np.mean(tm.face_normals[:, 2] > 0.9) > 0.99  # winding agrees with the normals
    # 40 x 40 mm observed, minus at most a 1.5 mm rim
    assert 37.0**2 <= surf.area_mm2() <= 40.5**2
    assert np.all(surf.weight >= 1.0)


def test_chunk_seams_are_merged():
    surf = SurfaceExtractor(_fused_plane(z=0.3, extent=40.0)).update()
    keys = np.round(surf.vertices_O / 1e-4).astype(np.int64)
    assert len(np.unique(keys, axis=0)) == surf.n_vertices
    tm = surf.to_trimesh()
    # one connected sheet across the 16 mm chunks
    assert len(tm.split(only_watertight=False)) == 1


def test_incremental_update_equals_full_extraction():
    tsdf = _fused_plane(z=0.3, extent=20.0)
    inc = SurfaceExtractor(tsdf)
    inc.update()
    _fused_plane(z=0.3, extent=60.0, seed=1, tsdf=tsdf)  # more area, some blocks revisited
    a = inc.update()
    b = SurfaceExtractor(tsdf).update()
    assert a.n_vertices == b.n_vertices and a.n_faces == b.n_faces
    # the same vertices (whole rows) and the same triangles, whatever their order
    np.testing.assert_array_equal(_rows_sorted(a.vertices_O), _rows_sorted(b.vertices_O))
    np.testing.assert_array_equal(_triangles_sorted(a), _triangles_sorted(b))


def _rows_sorted(x: np.ndarray) -> np.ndarray:
    return x[np.lexsort(x.T[::-1])]


def _triangles_sorted(surf) -> np.ndarray:
    """Each face as its three corner points (in its own winding, rotated to start at the
    smallest corner), the faces sorted: equal for two meshes of the same triangles."""
    corners = surf.vertices_O[surf.faces]  # (m, 3, 3)
    first = np.array([min(range(3), key=lambda k, c=c: tuple(c[k])) for c in corners])
    rolled = np.stack([np.roll(c, -k, axis=0) for c, k in zip(corners, first, strict=True)])
    return _rows_sorted(rolled.reshape(len(rolled), 9))


def test_unobserved_field_gives_an_empty_surface():
    surf = SurfaceExtractor(SparseTSDF()).update()
    assert surf.n_vertices == 0 and surf.n_faces == 0 and surf.area_mm2() == 0.0


def test_ply_round_trip_keeps_weights_and_opens_in_open3d(tmp_path):
    surf = SurfaceExtractor(_fused_plane(extent=12.0)).update()
    path = tmp_path / "s.ply"
    surf.write_ply(path)
    back = read_ply(path)
    np.testing.assert_array_equal(back.vertices_O, surf.vertices_O)
    np.testing.assert_array_equal(back.faces, surf.faces)
    np.testing.assert_array_equal(back.weight, surf.weight)
    assert b"property float scalar_weight" in path.read_bytes()[:600]
    import open3d as o3d

    m = o3d.io.read_triangle_mesh(str(path))
    assert len(m.vertices) == surf.n_vertices and len(m.triangles) == surf.n_faces
    assert len(surf.to_open3d().triangles) == surf.n_faces


def test_ply_re_saved_by_another_tool_reads_back(tmp_path):
    """A file re-saved as ASCII with the properties in another order and the faces as a
    variable-length list (as mesh tools write it) reads back to the same mesh."""
    from plyfile import PlyData, PlyElement

    surf = SurfaceExtractor(_fused_plane(extent=12.0)).update()
    path = tmp_path / "s.ply"
    surf.write_ply(path)
    original = PlyData.read(str(path))
    order = ["scalar_weight", "nz", "ny", "nx", "z", "y", "x"]
    data = original["vertex"].data
    vertex = np.empty(len(data), dtype=[(k, data.dtype[k].str) for k in order])
    for k in order:
        vertex[k] = data[k]
    faces = np.empty(surf.n_faces, dtype=[("vertex_indices", object)])
    faces["vertex_indices"] = [np.asarray(f, dtype=np.int32) for f in surf.faces]
    resaved = tmp_path / "resaved.ply"
    PlyData([PlyElement.describe(vertex, "vertex"),
             PlyElement.describe(faces, "face")], text=True).write(str(resaved))
    back = read_ply(resaved)
    np.testing.assert_array_equal(back.vertices_O, surf.vertices_O)
    np.testing.assert_array_equal(back.normals_O, surf.normals_O)
    np.testing.assert_array_equal(back.faces, surf.faces)
    np.testing.assert_array_equal(back.weight, surf.weight)
    no_weight = tmp_path / "no_weight.ply"
    xyz = np.empty(len(data), dtype=[(k, "<f8") for k in "xyz"])
    for k in "xyz":
        xyz[k] = data[k]
    PlyData([PlyElement.describe(xyz, "vertex"),
             PlyElement.describe(faces, "face")]).write(str(no_weight))
    with pytest.raises(MessageError, match="no_weight.ply.*scalar_weight"):
        read_ply(no_weight)


def test_surface_mesh_validates():
    with pytest.raises(MessageError, match="faces"):
        SurfaceMesh(np.zeros((3, 3)), [[0, 1, 5]], np.ones(3), np.zeros((3, 3)))
    with pytest.raises(MessageError, match="weight"):
        SurfaceMesh(np.zeros((3, 3)), [[0, 1, 2]], np.ones(2), np.zeros((3, 3)))
