"""The PLY writer packs triangle faces at once: the bytes are exactly those of plyfile's own
(face-by-face) writer, and the file reads back."""

from __future__ import annotations

import numpy as np
from plyfile import PlyData, PlyElement

from dm2.io.ply import read_mesh_ply, write_mesh_ply
from dm2.view.run_folder import read_layer_ply


def test_packed_faces_are_plyfiles_bytes(tmp_path):
    rng = np.random.default_rng(3)
    n = 60
    faces = rng.integers(0, n, (90, 3))
    fields = {"x": rng.random(n).astype(np.float32), "y": rng.random(n).astype(np.float32),
              "z": rng.random(n).astype(np.float32),
              "red": rng.integers(0, 255, n).astype(np.uint8),
              "scalar_signed_distance": rng.normal(0, 1, n).astype(np.float32),
              "scalar_class": rng.integers(0, 6, n).astype(np.float32)}
    write_mesh_ply(tmp_path / "a.ply", fields, faces, comments=["dm2 test"])
    vertex = np.empty(n, dtype=[(k, v.dtype.str) for k, v in fields.items()])
    for k, v in fields.items():
        vertex[k] = v
    face = np.empty(len(faces), dtype=[("vertex_indices", "<i4", (3,))])
    face["vertex_indices"] = faces
    PlyData([PlyElement.describe(vertex, "vertex"),
             PlyElement.describe(face, "face", len_types={"vertex_indices": "u1"})],
            text=False, byte_order="<", comments=["dm2 test"]).write(str(tmp_path / "b.ply"))
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    back, back_faces = read_mesh_ply(tmp_path / "a.ply")
    assert np.array_equal(back_faces, faces) and np.array_equal(back["red"], fields["red"])
    fast = read_layer_ply(tmp_path / "a.ply")
    assert np.array_equal(fast["faces"], faces)
    assert np.array_equal(fast["signed"], fields["scalar_signed_distance"])
