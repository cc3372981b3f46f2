"""Surface extraction from the sparse TSDF: incremental marching cubes, per-vertex weight.

The field is cut into chunks of ``CHUNK_BLOCKS**3`` blocks. Each chunk is gathered into a dense
sub-volume with a one-voxel apron on its upper faces and triangulated with
``skimage.measure.marching_cubes``, only in cubes whose eight corners were observed with weight
``>= min_weight``. Chunk meshes are cached; an update re-meshes only the chunks whose blocks
(or apron) were touched since the last extraction; :meth:`SurfaceExtractor.premesh` meshes
touched chunks ahead of time (a live loop's idle moments) so the next update has less to do,
with the same result. Vertices shared by neighbouring chunks are merged
when the chunks are assembled (only vertices on chunk faces are compared).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import map_coordinates

from dm2 import tsdf_kernels as K
from dm2.messages import MessageError
from dm2.tsdf import SparseTSDF
from dm2.tsdf_kernels import BLOCK

CHUNK_BLOCKS = 4
_MISSING = object()


def _chunks_of(blocks: np.ndarray) -> list[tuple[int, int, int]]:
    """Chunks whose mesh depends on ``blocks (k, 3)``, in a fixed order (a block is also the
    upper apron of the chunks below/behind it)."""
    chunks: set = set()
    if len(blocks):
        base = np.floor_divide(blocks, CHUNK_BLOCKS)
        at_low = (blocks - base * CHUNK_BLOCKS) == 0
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    shift = np.array([dx, dy, dz])
                    sel = np.all(at_low | (shift == 0), axis=1)
                    for c in map(tuple, (base[sel] - shift).tolist()):
                        chunks.add(c)
    return list(chunks)


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


class SurfaceExtractor:
    """Incremental marching cubes over a :class:`SparseTSDF`.

    Parameters
    ----------
    tsdf : the field to triangulate
    min_weight : cubes with any corner weight below this are left open (not observed)
    """

    def __init__(self, tsdf: SparseTSDF, min_weight: float = 1.0):
        self.tsdf = tsdf
        self.min_weight = float(min_weight)
        self._chunks: dict[tuple[int, int, int], tuple[np.ndarray, ...]] = {}
        self._first = True
        # pre-meshing (see premesh): block slots whose touch marks it consumed, chunks still
        # to mesh, and chunk meshes made ahead of the next update that are still current
        self._consumed = np.zeros(0, dtype=np.bool_)
        self._todo: dict[tuple[int, int, int], None] = {}
        self._premeshed: dict[tuple[int, int, int], tuple | None] = {}

    def update(self) -> SurfaceMesh:
        """Re-mesh chunks touched since the last call and return the whole surface."""
        n = self.tsdf.n_blocks
        fresh = np.flatnonzero(self.tsdf.touched[:n])
        for c in _chunks_of(K.unpack_keys(self.tsdf.block_keys[fresh])):
            self._premeshed.pop(c, None)  # touched after it was pre-meshed
        self.tsdf.touched[fresh] = False
        consumed = np.zeros(n, dtype=np.bool_)
        m = min(n, self._consumed.shape[0])
        consumed[:m] = self._consumed[:m]
        consumed[fresh] = True
        self._consumed[:] = False
        blocks = K.unpack_keys(self.tsdf.block_keys[np.flatnonzero(consumed)])
        if self._first:  # a new extractor meshes everything observed so far
            blocks, self._first = self.tsdf.block_coords(), False
        if len(blocks):
            for c in _chunks_of(blocks):
                m = self._premeshed.pop(c, _MISSING)
                self._chunks[c] = self._mesh_chunk(np.array(c)) if m is _MISSING else m
        self._premeshed.clear()
        self._todo.clear()
        return self.assemble()

    def premesh(self, stop=None) -> bool:
        """Mesh the touched chunks ahead of the next :meth:`update`, which then only meshes
        what was touched afterwards; the surface it returns is the same. Chunks touched since
        the previous call (the active region, touched again by the next profiles) wait for a
        later call.

        ``stop()`` is asked before each chunk (a few ms each); True makes it return False at
        once (call again later). Returns True when only the recently touched chunks wait.
        """
        n = self.tsdf.n_blocks
        fresh = np.flatnonzero(self.tsdf.touched[:n])
        if self._first:  # the first update meshes every block
            blocks = self.tsdf.block_coords() if not self._premeshed and not self._todo else \
                K.unpack_keys(self.tsdf.block_keys[fresh])
        else:
            blocks = K.unpack_keys(self.tsdf.block_keys[fresh])
        self.tsdf.touched[fresh] = False
        if self._consumed.shape[0] < n:
            grown = np.zeros(self.tsdf.touched.shape[0], dtype=np.bool_)
            grown[: self._consumed.shape[0]] = self._consumed
            self._consumed = grown
        self._consumed[fresh] = True
        hot = _chunks_of(blocks)
        for c in hot:
            self._premeshed.pop(c, None)
            self._todo[c] = None
        hot = set(hot)  # touched since the last call: likely touched again, meshed next call
        for c in [c for c in self._todo if c not in hot]:
            if stop is not None and stop():
                return False
            del self._todo[c]
            self._premeshed[c] = self._mesh_chunk(np.array(c))
        return True

    def _mesh_chunk(self, chunk: np.ndarray):
        from skimage.measure import marching_cubes

        n = CHUNK_BLOCKS * BLOCK
        origin = chunk * n
        d, w = self.tsdf.dense(origin, (n + 1, n + 1, n + 1))
        d[w <= 0] = self.tsdf.truncation_mm  # never updated: free space, never exactly level
        seen = w >= self.min_weight  # skimage meshes a cube only if all 8 corners are masked
        if not (np.any(d[seen] < 0) and np.any(d[seen] > 0)):
            return None
        vox = self.tsdf.voxel_mm
        try:
            verts, faces, normals, _ = marching_cubes(d, 0.0, spacing=(vox, vox, vox),
                                                      gradient_direction="descent", mask=seen,
                                                      allow_degenerate=False)
        except (ValueError, RuntimeError):
            return None  # no zero crossing inside the observed cubes
        # keep only triangles inside cubes whose eight corners were all observed
        cube = seen[:-1, :-1, :-1] & seen[1:, :-1, :-1] & seen[:-1, 1:, :-1] & seen[:-1, :-1, 1:] \
            & seen[1:, 1:, :-1] & seen[1:, :-1, 1:] & seen[:-1, 1:, 1:] & seen[1:, 1:, 1:]
        centre = verts[faces].mean(axis=1) / vox
        ijk = np.clip(np.floor(centre).astype(np.int64), 0, n - 1)
        faces = faces[cube[ijk[:, 0], ijk[:, 1], ijk[:, 2]]]
        if not len(faces):
            return None
        used = np.unique(faces)
        remap = np.full(len(verts), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        verts, normals, faces = verts[used], normals[used], remap[faces]
        wv = map_coordinates(w, (verts / vox).T, order=1, mode="nearest").astype(np.float32)
        verts_O = verts + (origin + 0.5) * vox  # voxel centres sit at (i + 0.5) * voxel
        # vertices on the chunk's faces are shared with a neighbour; only they are merged
        g = verts / vox
        border = np.any((np.abs(g) < 1e-4) | (np.abs(g - n) < 1e-4), axis=1)
        return verts_O, faces.astype(np.int64), wv, -normals.astype(np.float64), border

    def assemble(self) -> SurfaceMesh:
        parts = [m for m in self._chunks.values() if m is not None]
        if not parts:
            return SurfaceMesh.empty()
        offs = np.cumsum([0] + [len(p[0]) for p in parts])
        verts = np.concatenate([p[0] for p in parts])
        faces = np.concatenate([p[1] + o for p, o in zip(parts, offs[:-1], strict=True)])
        weight = np.concatenate([p[2] for p in parts])
        normals = np.concatenate([p[3] for p in parts])
        # merge vertices duplicated on chunk borders (only border vertices can be: a sort of
        # that small subset, not of the whole surface)
        on_border = np.flatnonzero(np.concatenate([p[4] for p in parts]))
        key = np.round(verts[on_border] / (1e-4 * self.tsdf.voxel_mm)).astype(np.int64)
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        target = np.arange(len(verts))
        target[on_border] = on_border[first][inverse.ravel()]  # each copy -> its first copy
        kept = np.ones(len(verts), dtype=bool)
        kept[on_border] = False
        kept[on_border[first]] = True
        new_index = np.cumsum(kept) - 1
        faces = new_index[target[faces]]
        keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & \
            (faces[:, 0] != faces[:, 2])
        nrm = normals[kept]
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        return SurfaceMesh(verts[kept], faces[keep], weight[kept], nrm)
