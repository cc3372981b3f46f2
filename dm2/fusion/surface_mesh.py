"""The reconstructed surface as a data contract: :class:`SurfaceMesh` (vertices, faces,
per-vertex fused weight and normals in ``O``) and its binary PLY form (:func:`read_ply`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dm2.core.messages import MessageError


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
        """Binary little-endian PLY with normals and a ``scalar_weight`` vertex property."""
        path = Path(path)
        n, m = self.n_vertices, self.n_faces
        header = (
            "ply\nformat binary_little_endian 1.0\ncomment frame O, units mm\n"
            f"element vertex {n}\nproperty double x\nproperty double y\nproperty double z\n"
            "property double nx\nproperty double ny\nproperty double nz\n"
            "property float scalar_weight\n"
            f"element face {m}\nproperty list uchar int vertex_indices\nend_header\n"
        )
        vdt = np.dtype([("p", "<f8", 3), ("n", "<f8", 3), ("w", "<f4")])
        vert = np.empty(n, dtype=vdt)
        vert["p"], vert["n"], vert["w"] = self.vertices_O, self.normals_O, self.weight
        fdt = np.dtype([("k", "u1"), ("i", "<i4", 3)])
        face = np.empty(m, dtype=fdt)
        face["k"], face["i"] = 3, self.faces
        tmp = path.with_name(path.name + ".part")
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(vert.tobytes())
            fh.write(face.tobytes())
        tmp.replace(path)


def read_ply(path: str | Path) -> SurfaceMesh:
    """Read a PLY written by :meth:`SurfaceMesh.write_ply`."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if end < 0:
        raise MessageError(f"{path}: not a PLY file (no end_header)")
    header = data[:end].decode("ascii", "replace").splitlines()
    counts = {ln.split()[1]: int(ln.split()[2]) for ln in header if ln.startswith("element")}
    if "scalar_weight" not in " ".join(header):
        raise MessageError(f"{path}: PLY has no scalar_weight property")
    n, m = counts.get("vertex", 0), counts.get("face", 0)
    vdt = np.dtype([("p", "<f8", 3), ("n", "<f8", 3), ("w", "<f4")])
    fdt = np.dtype([("k", "u1"), ("i", "<i4", 3)])
    off = end + len(b"end_header\n")
    vert = np.frombuffer(data, vdt, n, off)
    face = np.frombuffer(data, fdt, m, off + n * vdt.itemsize)
    return SurfaceMesh(vert["p"], face["i"].astype(np.int64), vert["w"], vert["n"])
