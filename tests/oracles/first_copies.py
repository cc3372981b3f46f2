"""Plain numpy statement of the chunk-border vertex merge (dm2.fusion.surface_assemble's
``_first_copies``): a stable sort of the rounded positions; each group's first entry is the
first copy of every vertex in it."""

from __future__ import annotations

import numpy as np


def first_copies(verts: np.ndarray, on_border: np.ndarray, step: float) -> np.ndarray:
    key = np.round(verts[on_border] / step).astype(np.int64)
    order = np.lexsort(key.T[::-1])  # stable: a group's first entry is its first copy
    sorted_key = key[order]
    starts = np.ones(len(order), dtype=bool)
    starts[1:] = np.any(sorted_key[1:] != sorted_key[:-1], axis=1)
    first = order[np.flatnonzero(starts)]
    target = np.arange(len(verts))
    target[on_border[order]] = on_border[first[np.cumsum(starts) - 1]]
    return target
