"""The reconstructed surface as a data contract: :class:`SurfaceMesh` (vertices, faces,
per-vertex fused weight and normals in ``O``) and its binary PLY form (:func:`read_ply`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dm2.core.messages import MessageError
from dm2.io.ply import read_mesh_ply, write_mesh_ply


@dataclass(frozen=True)
class SurfaceMesh:
    """A reconstructed surface in the work-object frame.

    Attributes
    ----------
    vertices_O : (n, 3) float64 [mm]
    faces : (m, 3) int64, vertex indices, counter-clockwise seen from outside
    weight : (n,) float32, fused TSDF weight at each vertex (confidence)
    normals_O : (n, 3) float64, unit outward normals (pointing into observed free space)
    """

    vertices_O: np.ndarray
    faces: np.ndarray
    weight: np.ndarray
    normals_O: np.ndarray

    def __post_init__(self):
        v = np.ascontiguousarray(self.vertices_O, dtype=np.float64).reshape(-1, 3)
        n = v.shape[0]
        f = np.ascontiguousarray(self.faces, dtype=np.int64).reshape(-1, 3)
        w = np.ascontiguousarray(self.weight, dtype=np.float32)
        nrm = np.ascontiguousarray(self.normals_O, dtype=np.float64).reshape(-1, 3)
        if w.shape != (n,) or nrm.shape != (n, 3):
            raise MessageError(f"SurfaceMesh: weight {w.shape} / normals {nrm.shape} do not "
                               f"match {n} vertices")
        if f.size and (f.min() < 0 or f.max() >= n):
            raise MessageError("SurfaceMesh.faces: vertex index out of range")
        if not np.all(np.isfinite(v)):
            raise MessageError("SurfaceMesh.vertices_O: contains NaN or infinite values")
        for name, arr in (("vertices_O", v), ("faces", f), ("weight", w), ("normals_O", nrm)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @classmethod
    def empty(cls) -> SurfaceMesh:
        return cls(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.float32),
                   np.zeros((0, 3)))

    @property
    def n_vertices(self) -> int:
        return int(self.vertices_O.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    def area_mm2(self) -> float:
        if not self.n_faces:
            return 0.0
        a, b, c = (self.vertices_O[self.faces[:, k]] for k in range(3))
        return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())

    def to_trimesh(self):
        import trimesh

        return trimesh.Trimesh(vertices=self.vertices_O, faces=self.faces,
                               vertex_normals=self.normals_O, process=False)

    def to_open3d(self):
        import open3d as o3d

        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices_O.copy()),
                                      o3d.utility.Vector3iVector(self.faces.astype(np.int32)))
        m.vertex_normals = o3d.utility.Vector3dVector(self.normals_O.copy())
        return m

    def write_ply(self, path: str | Path) -> None:
        """Binary PLY in ``O`` [mm]: double ``x y z`` and ``nx ny nz``, float ``scalar_weight``."""
        v, nrm = self.vertices_O, self.normals_O
        write_mesh_ply(path, {"x": v[:, 0], "y": v[:, 1], "z": v[:, 2], "nx": nrm[:, 0],
                              "ny": nrm[:, 1], "nz": nrm[:, 2],
                              "scalar_weight": self.weight.astype(np.float32)},
                       self.faces, comments=["frame O, units mm"])


def read_ply(path: str | Path) -> SurfaceMesh:
    """Read a fused surface PLY (:meth:`SurfaceMesh.write_ply`, or the same fields re-saved)."""
    fields, faces = read_mesh_ply(path)
    missing = [k for k in ("x", "y", "z", "nx", "ny", "nz", "scalar_weight") if k not in fields]
    if missing:
        raise MessageError(f"{path}: PLY has no vertex properties {', '.join(missing)}")
    xyz = np.column_stack([fields[k] for k in "xyz"]).astype(np.float64)
    nrm = np.column_stack([fields[k] for k in ("nx", "ny", "nz")]).astype(np.float64)
    return SurfaceMesh(xyz, faces, fields["scalar_weight"].astype(np.float32), nrm)
