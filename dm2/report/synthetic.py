"""A synthetic monitored run of a chosen size, for the report's cost benchmark and tests.

:func:`synthetic_run` builds ``n_layers`` layer results on one shared grid mesh (the report's
cost per layer is the mesh it writes and draws, not how the mesh came about) with many small
defect regions: each region lives a few layers at a seeded random place, so the real
:class:`~dm2.defects.track.RegionTracker` turns them into at least ``n_tracks`` tracks. Real-time
alarms are placed at some of the regions. Seeded: the same arguments give the same run.
"""

from __future__ import annotations

import numpy as np

from dm2.defects.classify import CLASS_NAMES
from dm2.defects.deviation import LayerDeviation
from dm2.defects.layer_analysis import LayerResult
from dm2.defects.segment import Region
from dm2.defects.track import RegionTracker
from dm2.reference.height_map import ReferenceMap

KINDS = ("overbuild", "underbuild", "local_overbuild", "local_underbuild")


def grid_mesh(size_mm: float, step_mm: float):
    """(vertices_O (n, 3), faces (m, 3)) of a flat square grid from (10, 10) mm."""
    n = int(round(size_mm / step_mm)) + 1
    x = 10.0 + np.arange(n) * step_mm
    xx, yy = np.meshgrid(x, x)
    v = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(n * n)])
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return v, np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])]), n


def synthetic_run(n_layers: int = 124, n_tracks: int = 1000, size_mm: float = 100.0,
                  step_mm: float = 0.5, seed: int = 7, layer_mm: float = 0.8):
    """``(results, tracks, realtime)``: LayerResults, the tracker's tracks and a ``realtime``
    report section with one alarm per ten tracks."""
    rng = np.random.default_rng(seed)
    v, faces, n = grid_mesh(size_mm, step_mm)
    weight = np.full(len(v), 10.0)
    area = np.full(len(v), step_mm * step_mm)
    foot = v.copy()
    ref = ReferenceMap(np.zeros((int(size_mm / 0.25) + 80,) * 2), 0.25, 0)
    births = np.sort(rng.integers(0, n_layers, n_tracks + n_tracks // 10))
    lives = rng.integers(1, 6, len(births))
    centres = rng.uniform(15.0, size_mm + 5.0, (len(births), 2))
    kinds = rng.integers(0, len(KINDS), len(births))
    amp = rng.uniform(0.3, 1.2, len(births)) * np.where(kinds % 2 == 0, 1.0, -1.0)
    tracker = RegionTracker(margin_mm=0.0)
    results, alarms = [], []
    for layer in range(n_layers):
        z = (layer + 1) * layer_mm
        sd = rng.normal(0.0, 0.05, len(v))
        code = np.zeros(len(v), np.int8)
        code[rng.random(len(v)) < 0.01] = CLASS_NAMES.index("unobserved")
        alive = np.flatnonzero((births <= layer) & (layer < births + lives))
        regions = []
        for k in alive:
            i, j = ((centres[k] - 10.0) / step_mm).astype(int)
            rr = 2 + (layer - births[k]) % 3
            rows = np.clip(np.arange(j - rr, j + rr + 1), 0, n - 1)
            cols = np.clip(np.arange(i - rr, i + rr + 1), 0, n - 1)
            vid = np.unique((rows[:, None] * n + cols[None, :]).ravel())
            kind = KINDS[kinds[k]]
            d = amp[k] * (1.0 + 0.1 * (layer - births[k]))
            sd[vid] = d
            code[vid] = CLASS_NAMES.index(kind)
            pts = v[vid] + [0.0, 0.0, z]
            lo, hi = pts.min(axis=0), pts.max(axis=0) + [0.0, 0.0, abs(d)]
            regions.append(Region(layer, kind, float(area[vid].sum()), lo, hi,
                                  float(hi[2] - lo[2]), float(d), float(0.7 * d),
                                  pts.mean(axis=0), vid))
            if layer == births[k] and k % 10 == 0:
                alarms.append({"stamp_s": 60.0 * layer + 30.0, "kind": kind.replace("local_", ""),
                               "area_mm2": float(area[vid].sum()),
                               "centroid_xy_O_mm": [float(c) for c in centres[k]],
                               "first_flag_s": 60.0 * layer + 29.5, "delay_s": 0.5})
        ids = tracker.update(layer, regions)
        dev = LayerDeviation(layer, v, faces, weight, sd, foot, code, np.zeros(len(v)),
                             np.zeros(len(v)), area, stamp_s=60.0 * (layer + 1))
        results.append(LayerResult(layer, dev, ref, regions, ids, {}))
    tracker.finish()
    realtime = {"frame_sets": 60 * n_layers * 3, "latency_ms_p50": 0.3, "latency_ms_p99": 6.0,
                "alarms": alarms}
    return results, tracker.tracks, realtime
