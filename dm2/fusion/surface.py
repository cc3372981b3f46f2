"""Surface extraction from the sparse TSDF: incremental marching cubes, per-vertex weight.

The field is cut into chunks of ``CHUNK_BLOCKS**3`` blocks. Each chunk is gathered into a dense
sub-volume with a one-voxel apron on its upper faces and triangulated with skimage's marching
cubes (compiled: :mod:`dm2.fusion.chunk_mesh`), only in cubes whose eight corners were
observed with weight ``>= min_weight``. Chunk meshes are cached; an update re-meshes only the
chunks whose blocks (or apron) were touched since the last extraction;
:meth:`SurfaceExtractor.premesh` meshes touched chunks ahead of time (a live loop's idle
moments) so the next update has less to do, with the same result. Vertices shared by
neighbouring chunks are merged when the chunks are assembled (only vertices on chunk faces
are compared).

:meth:`SurfaceExtractor.gather` splits an update in two: on the fusion thread it only copies
the small dense TSDF/weight boxes of the chunks to re-mesh (:class:`ChunkVolume`) and returns
a :class:`PendingSurface`; marching cubes and assembly run when its :meth:`~PendingSurface.
result` is first asked for, on whichever thread asks (a live session's worker). The field may
go on changing meanwhile: the copies are the field at the gather, so the surface is the one an
immediate :meth:`~SurfaceExtractor.update` would have returned.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from dm2.fusion.chunk_mesh import chunk_surface
from dm2.fusion.surface_assemble import assemble
from dm2.fusion.surface_mesh import SurfaceMesh, read_ply
from dm2.fusion.tsdf import kernels as K
from dm2.fusion.tsdf.field import SparseTSDF
from dm2.fusion.tsdf.kernels import BLOCK

__all__ = ["CHUNK_BLOCKS", "ChunkVolume", "PendingSurface", "SurfaceExtractor", "SurfaceMesh",
           "mesh_volume", "read_ply"]

CHUNK_BLOCKS = 4
_MISSING = object()
# Chunk volumes are meshed by this many threads (the marching-cubes kernel releases the GIL)
# when a surface has at least MIN_PARALLEL_CHUNKS of them; the surface is the same.
MESH_THREADS = 2 if (os.cpu_count() or 1) >= 2 else 1
MIN_PARALLEL_CHUNKS = 8
_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def _resolved_all(parts: list) -> list:
    """The chunk meshes of ``parts`` in order; with ``MESH_THREADS`` 2 the calling thread meshes
    every other volume and a pool thread the rest."""
    global _POOL
    todo = [p for p in parts if isinstance(p, ChunkVolume)]
    if MESH_THREADS > 1 and len(todo) >= MIN_PARALLEL_CHUNKS:
        with _POOL_LOCK:
            if _POOL is None:
                _POOL = ThreadPoolExecutor(MESH_THREADS - 1, thread_name_prefix="surface-mesh")
        other = _POOL.submit(lambda: [v.mesh() for v in todo[1::2]])
        for v in todo[0::2]:
            v.mesh()
        other.result()
    return [_resolved(p) for p in parts]


def _chunks_of(blocks: np.ndarray) -> list[tuple[int, int, int]]:
    """Chunks whose mesh depends on ``blocks (k, 3)``, sorted (a block is also the upper apron
    of the chunks below/behind it)."""
    if not len(blocks):
        return []
    base = np.floor_divide(blocks, CHUNK_BLOCKS)
    at_low = (blocks - base * CHUNK_BLOCKS) == 0
    found = [base]
    for shift in np.array([(dx, dy, dz) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)])[1:]:
        found.append(base[np.all(at_low | (shift == 0), axis=1)] - shift)
    c = np.concatenate(found).astype(np.int64)  # packed like block keys: one int64, sorted
    key = np.unique(K.pack_key(c[:, 0], c[:, 1], c[:, 2]))
    return list(map(tuple, K.unpack_keys(key).tolist()))


def mesh_volume(d: np.ndarray, w: np.ndarray, origin: np.ndarray, voxel_mm: float,
                truncation_mm: float, min_weight: float):
    """Marching cubes of one chunk's dense box; None when it holds no observed surface.

    Parameters
    ----------
    d, w : (n+1, n+1, n+1) float32, signed distance [mm] and weight (``d`` is modified)
    origin : (3,) int, the box's first voxel index
    voxel_mm, truncation_mm, min_weight : the field's voxel edge, truncation and the weight
        a cube's eight corners need to be meshed

    Returns
    -------
    (vertices_O (k, 3) [mm], faces (f, 3) int64, weight (k,) float32, normals_O (k, 3),
    on_border (k,) bool) or None
    """
    mesh = chunk_surface(d, w, truncation_mm, min_weight, voxel_mm)
    if mesh is None:
        return None
    verts, faces, normals, weight, on_border = mesh
    verts_O = verts + (origin + 0.5) * voxel_mm  # voxel centres sit at (i + 0.5) * voxel
    # vertices on the chunk's faces are shared with a neighbour; only they are merged
    return verts_O, faces, weight, -normals.astype(np.float64), on_border


class ChunkVolume:
    """A chunk's dense TSDF/weight box, meshed once, on first use.

    ``box`` is :func:`mesh_volume`'s arguments (the box copied at a gather), or a function
    that returns them (the box copied when it is meshed, on the meshing thread)."""

    __slots__ = ("_args", "_mesh", "_lock")

    def __init__(self, box):
        self._args = box
        self._mesh = None
        self._lock = threading.Lock()

    def mesh(self):
        """The chunk's mesh tuple (see :func:`mesh_volume`) or None."""
        with self._lock:
            if self._args is not None:
                args = self._args() if callable(self._args) else self._args
                self._mesh, self._args = mesh_volume(*args), None  # frees the copies
            return self._mesh


def _resolved(part):
    return part.mesh() if isinstance(part, ChunkVolume) else part


class PendingSurface:
    """The surface of one gather: chunk meshes and chunk volumes still to mesh.

    :meth:`result` meshes the volumes and assembles the surface on the calling thread, once
    (later calls, from any thread, return the same :class:`SurfaceMesh`).
    """

    def __init__(self, parts: list, voxel_mm: float):
        self._parts = parts
        self._voxel_mm = float(voxel_mm)
        self._surface: SurfaceMesh | None = None
        self._lock = threading.Lock()

    @property
    def n_to_mesh(self) -> int:
        """Chunks still to mesh (0 once resolved)."""
        if self._parts is None:
            return 0
        return sum(isinstance(p, ChunkVolume) for p in self._parts)

    def result(self) -> SurfaceMesh:
        with self._lock:
            if self._surface is None:
                self._surface = assemble(_resolved_all(self._parts), self._voxel_mm)
                self._parts = None
            return self._surface


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
        self._chunks: dict[tuple[int, int, int], object] = {}  # mesh tuple, None or volume
        self._first = True
        # pre-meshing (see premesh): block slots whose touch marks it consumed, chunks still
        # to mesh, and chunk meshes made ahead of the next update that are still current
        self._consumed = np.zeros(0, dtype=np.bool_)
        self._todo: dict[tuple[int, int, int], None] = {}
        self._premeshed: dict[tuple[int, int, int], tuple | None] = {}

    def update(self) -> SurfaceMesh:
        """Re-mesh chunks touched since the last call and return the whole surface (the boxes
        are copied by the threads that mesh them: the field does not change meanwhile)."""
        return self._gather(copy_now=False).result()

    def gather(self) -> PendingSurface:
        """What :meth:`update` does up to marching cubes: copy the boxes of the chunks touched
        since the last call (meshes made by :meth:`premesh` are taken as they are); the
        returned surface is meshed and assembled when asked for."""
        return self._gather(copy_now=True)

    def _gather(self, copy_now: bool) -> PendingSurface:
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
                self._chunks[c] = self._volume(np.array(c), copy_now) if m is _MISSING else m
        self._premeshed.clear()
        self._todo.clear()
        return PendingSurface(self._chunks_in_order(), self.tsdf.voxel_mm)

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
            self._premeshed[c] = self._volume(np.array(c)).mesh()
        return True

    def _volume(self, chunk: np.ndarray, copy_now: bool = True) -> ChunkVolume:
        """One chunk's dense box (with its one-voxel upper apron), copied now or when meshed."""
        n = CHUNK_BLOCKS * BLOCK
        origin = chunk * n

        def copy():
            d, w = self.tsdf.dense(origin, (n + 1, n + 1, n + 1))
            return d, w, origin, self.tsdf.voxel_mm, self.tsdf.truncation_mm, self.min_weight

        return ChunkVolume(copy() if copy_now else copy)

    def assemble(self) -> SurfaceMesh:
        """The surface from the chunk meshes cached now (volumes still pending are meshed)."""
        return assemble(_resolved_all(self._chunks_in_order()), self.tsdf.voxel_mm)

    def _chunks_in_order(self) -> list:
        """The chunks' meshes or volumes sorted by chunk coordinates: the surface's vertex
        order then depends only on the field, not on the order blocks were allocated in."""
        return [self._chunks[c] for c in sorted(self._chunks)]
