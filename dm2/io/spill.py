"""Finished layers' arrays kept on disk, not in memory: the memory of a build stays bounded.

Every layer leaves arrays of the whole part behind: the fused surface mesh
(:class:`~dm2.fusion.fusion.LayerSurface`), its deviation
(:class:`~dm2.defects.deviation.LayerDeviation`: vertices, faces and a dozen per-vertex
fields, about 180 bytes a vertex) and the reference height map. A tall part re-meshes its whole
surface every layer, so keeping them all grows with layers times surface: the 124-layer twisted
tower held about 3 GB of deviations alone by its last layer. Only the report at the end (and
the bench's scoring) reads old layers again, one at a time.

:class:`SpillStore` writes such an object to a private scratch folder once its layer is final
and hands back a :class:`Spilled` proxy to keep in its place. The proxy reads the file back
when anything else is first asked of it and keeps the most recently read object, so a pass
over the layers in order holds one layer at a time. The round trip is a pickle of the same
object: every array comes back bit for bit. The folder is removed when the store is closed or
garbage-collected (a proxy keeps its store alive).
"""

from __future__ import annotations

import pickle
import shutil
import tempfile
import threading
import weakref
from pathlib import Path

SCRATCH_PREFIX = "dm2-layers-"


_cache_lock = threading.Lock()
_cache: list = [None, None]  # [path, object] of the object read most recently


def _read(path: Path):
    with _cache_lock:
        if _cache[0] == path:
            return _cache[1]
    with open(path, "rb") as fh:
        obj = pickle.load(fh)
    with _cache_lock:
        _cache[0], _cache[1] = path, obj
    return obj


class Spilled:
    """Stands for an object written to ``path``: ``layer`` and ``n_vertices`` are at hand,
    any other attribute reads the object back.

    Pickled (e.g. to the live report's child process) it stays a path: the other process reads
    the file itself, while this one (which owns the folder) lives.
    """

    __slots__ = ("path", "layer", "n_vertices", "_owner")

    def __init__(self, path: Path, layer: int, n_vertices: int, owner=None):
        self.path = Path(path)
        self.layer = int(layer)
        self.n_vertices = int(n_vertices)
        self._owner = owner  # the SpillStore: its folder lives as long as a proxy does

    def load(self):
        """The object itself (read from disk unless it was the last one read)."""
        return _read(self.path)

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self.load(), name)

    def __reduce__(self):
        return (Spilled, (self.path, self.layer, self.n_vertices))

    def __repr__(self) -> str:
        return f"Spilled(layer={self.layer}, n_vertices={self.n_vertices}, {self.path})"


class SpillStore:
    """Writes finished layers' objects to a scratch folder (see the module docstring).

    Parameters
    ----------
    keep_layers : how many of the newest layers keep their objects in memory (for
        :meth:`spill_old`)
    scratch_dir : folder to make the scratch folder in (default: the system's temporary one)
    """

    def __init__(self, keep_layers: int, scratch_dir: str | Path | None = None):
        if keep_layers < 1:
            raise ValueError(f"SpillStore: keep_layers must be >= 1, got {keep_layers}")
        self.keep_layers = int(keep_layers)
        self._root = Path(tempfile.mkdtemp(prefix=SCRATCH_PREFIX, dir=scratch_dir))
        self._finalizer = weakref.finalize(self, shutil.rmtree, str(self._root), True)
        self.bytes_written = 0
        self._count = 0

    @property
    def folder(self) -> Path:
        return self._root

    def spill_old(self, items: list, attr: str, ready=None) -> None:
        """Spill attribute ``attr`` of every item but the newest :attr:`keep_layers` (only
        where ``ready(value)`` holds, when given)."""
        for item in items[:max(len(items) - self.keep_layers, 0)]:
            value = getattr(item, attr)
            if not isinstance(value, Spilled) and (ready is None or ready(value)):
                setattr(item, attr, self.spill(value))

    def spill(self, obj) -> Spilled:
        """Write ``obj`` (with a ``layer``; ``n_vertices`` if it has one) to disk; returns the
        proxy to keep instead."""
        self._count += 1
        layer = int(getattr(obj, "layer", -1))
        path = self._root / f"{type(obj).__name__}_{layer:05d}_{self._count:06d}.pickle"
        data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        path.write_bytes(data)
        self.bytes_written += len(data)
        return Spilled(path, layer, int(getattr(obj, "n_vertices", 0)), self)

    def close(self) -> None:
        """Remove the scratch folder (spilled objects can no longer be read)."""
        with _cache_lock:
            if _cache[0] is not None and Path(_cache[0]).parent == self._root:
                _cache[0] = _cache[1] = None
        self._finalizer()
