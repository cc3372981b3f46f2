"""Finished layers' deviations kept on disk, not in memory: the memory of a build stays bounded.

Every analysed layer leaves a :class:`~dm2.defects.deviation.LayerDeviation` of its whole
surface (vertices, faces and a dozen per-vertex fields, about 180 bytes a vertex). A tall part
re-meshes its whole surface every layer, so keeping them all grows with layers times surface:
the 124-layer twisted tower held about 3 GB of them by its last layer. Only the report at the
end (and the bench's scoring) reads old layers again, one at a time.

:class:`LayerSpill` writes a layer's deviation to a private scratch folder once it is final
(older than the tracker's confirmation window, which may still renumber the layer's regions;
those live on the :class:`~dm2.defects.layer_analysis.LayerResult`, not on the deviation) and
puts a :class:`SpilledDeviation` in its place. That proxy reads the file back when a field is
first asked for and keeps the most recently read layer, so a pass over the layers in order holds
one layer at a time. The round trip is a pickle of the same object: every array comes back bit
for bit. The folder is removed when the spill is closed or garbage-collected.
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
_cache: list = [None, None]  # [path, LayerDeviation] of the layer read most recently


def _read(path: Path):
    with _cache_lock:
        if _cache[0] == path:
            return _cache[1]
    with open(path, "rb") as fh:
        deviation = pickle.load(fh)
    with _cache_lock:
        _cache[0], _cache[1] = path, deviation
    return deviation


class SpilledDeviation:
    """Stands for a LayerDeviation written to ``path``: any other attribute reads it back.

    Pickled (e.g. to the live report's child process) it stays a path: the other process reads
    the file itself, while this one (which owns the folder) lives.
    """

    __slots__ = ("path", "layer", "n_vertices", "_owner")

    def __init__(self, path: Path, layer: int, n_vertices: int, owner=None):
        self.path = Path(path)
        self.layer = int(layer)
        self.n_vertices = int(n_vertices)
        self._owner = owner  # the LayerSpill: its folder lives as long as a proxy does

    def load(self):
        """The LayerDeviation itself (read from disk unless it was the last one read)."""
        return _read(self.path)

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self.load(), name)

    def __reduce__(self):
        return (SpilledDeviation, (self.path, self.layer, self.n_vertices))

    def __repr__(self) -> str:
        return f"SpilledDeviation(layer={self.layer}, n_vertices={self.n_vertices}, {self.path})"


class LayerSpill:
    """Writes final layers' deviations to a scratch folder (see the module docstring).

    Parameters
    ----------
    keep_layers : the newest this many layer results keep their deviation in memory
    scratch_dir : folder to make the scratch folder in (default: the system's temporary one)
    """

    def __init__(self, keep_layers: int, scratch_dir: str | Path | None = None):
        if keep_layers < 1:
            raise ValueError(f"LayerSpill: keep_layers must be >= 1, got {keep_layers}")
        self.keep_layers = int(keep_layers)
        self._root = Path(tempfile.mkdtemp(prefix=SCRATCH_PREFIX, dir=scratch_dir))
        self._finalizer = weakref.finalize(self, shutil.rmtree, str(self._root), True)
        self.bytes_written = 0

    @property
    def folder(self) -> Path:
        return self._root

    def spill_old(self, results: list) -> None:
        """Spill the deviation of every result but the newest :attr:`keep_layers`."""
        for res in results[:max(len(results) - self.keep_layers, 0)]:
            if not isinstance(res.deviation, SpilledDeviation):
                res.deviation = self.spill(res.deviation)

    def spill(self, deviation) -> SpilledDeviation:
        """Write ``deviation`` to disk; returns the proxy to keep instead."""
        path = self._root / f"layer_{int(deviation.layer):05d}.pickle"
        data = pickle.dumps(deviation, protocol=pickle.HIGHEST_PROTOCOL)
        path.write_bytes(data)
        self.bytes_written += len(data)
        return SpilledDeviation(path, int(deviation.layer), int(deviation.n_vertices), self)

    def close(self) -> None:
        """Remove the scratch folder (spilled layers can no longer be read)."""
        with _cache_lock:
            if _cache[0] is not None and Path(_cache[0]).parent == self._root:
                _cache[0] = _cache[1] = None
        self._finalizer()
