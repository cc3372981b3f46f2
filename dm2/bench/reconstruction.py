"""How far the reconstructed surface lies from the twin's true surface, layer by layer.

The twin writes each layer's true top surface as ``truth/layer_NNN.ply``: its height field's
cell centres as a regular grid of vertices (row-major, x fastest), each quad split into the
triangles a-b-d and a-d-c along the diagonal from (i, j) to (i + 1, j + 1)
(``twin.world.heightfield.HeightField.to_mesh``). Such a grid mesh is searched in place by
the exact search the deviation from the reference uses (:func:`grid_mesh_distance`:
:func:`dm2.defects.deviation.closest_on_grid`, unbounded). Any other mesh goes through
Open3D's ``RaycastingScene.compute_distance`` (a BVH; it holds the GIL and builds a tree per
layer, ``benchmarks/reconstruction_check.py`` measures both).

:func:`truth_checks` also asks it of each track's flagged vertices, beside their deviation from
the reference: whether the part itself stands off the reference there, or the measurement does.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2.defects.classify import CLASS_NAMES
from dm2.defects.deviation import closest_on_grid
from dm2.io.ply import read_mesh_ply

CROP_MM = 1.0  # vertices this close to the truth's xy extent are not compared (it is cropped)
GRID_TOL_MM = 1e-6  # a grid's vertex coordinates agree with its spacing within this
# a track's flagged vertices lie closer than this share of their |deviation| to the true
# surface: the part itself stands off the reference there (truth_checks)
PART_DEVIATES_SHARE = 0.5
# a track is drift in a layer when the true surface stands off the reference the run used by at
# least the tolerance, in the track's sign, under this share of its area there (truth_checks)
DRIFT_SHARE = 0.5


def grid_of_mesh(vertices: np.ndarray, faces: np.ndarray):
    """``(heights_mm (H, W), x0_mm, y0_mm, cell_mm)`` when ``vertices`` (H*W, 3) [mm] and
    ``faces`` (m, 3) are a grid mesh as the module docstring describes, else None."""
    v = np.asarray(vertices, dtype=np.float64)
    n = v.shape[0]
    if n < 4 or faces.shape[0] == 0:
        return None
    x0, y0 = v[0, 0], v[0, 1]
    W = int(np.argmax(v[:, 1] > y0 + GRID_TOL_MM)) or n  # first vertex of the second row
    H = n // W
    if W < 2 or H < 2 or H * W != n:
        return None
    cell = v[1, 0] - x0
    if cell <= GRID_TOL_MM:
        return None
    g = v.reshape(H, W, 3)
    ii, jj = np.arange(W) * cell + x0, np.arange(H) * cell + y0
    if (np.abs(g[:, :, 0] - ii[None, :]).max() > 1e3 * GRID_TOL_MM
            or np.abs(g[:, :, 1] - jj[:, None]).max() > 1e3 * GRID_TOL_MM):
        return None
    a = (np.arange(H - 1)[:, None] * W + np.arange(W - 1)[None, :]).ravel()
    expected = np.concatenate([np.column_stack([a, a + 1, a + W + 1]),
                               np.column_stack([a, a + W + 1, a + W])])
    if faces.shape != expected.shape or not np.array_equal(faces, expected):
        return None
    return np.ascontiguousarray(g[:, :, 2]), float(x0), float(y0), float(cell)


def grid_mesh_distance(points, h, x0, y0, cell):
    """Unsigned distance [mm] (n,) of ``points`` (n, 3) [mm] to the grid mesh of heights ``h``
    (H, W) with vertex (i, j) at (x0 + i cell, y0 + j cell, h[j, i]), exact (the deviation's
    own search, :func:`dm2.defects.deviation.closest_on_grid`, unbounded)."""
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    dist, _ = closest_on_grid(p, np.ascontiguousarray(h, np.float64), x0 / cell, y0 / cell,
                              cell, np.inf)
    return np.abs(dist)


def mesh_distance(points_O: np.ndarray, vertices_O: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unsigned distance [mm] (n,) of ``points_O`` (n, 3) to the triangle mesh
    (``vertices_O`` (m, 3) [mm], ``faces`` (f, 3)): in place on a grid mesh, else Open3D."""
    p = np.ascontiguousarray(points_O, dtype=np.float64).reshape(-1, 3)
    grid = grid_of_mesh(vertices_O, faces)
    if grid is not None:
        return grid_mesh_distance(p, *grid)
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices_O, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy().astype(
        np.float64)


def _truth_layers(results, truth_dir: Path):
    """``(result, truth_O (m, 3) [mm], faces, lo (2,), hi (2,))`` for each layer result with
    a true surface in ``truth_dir``; ``lo, hi``: the truth's xy extent less ``CROP_MM``."""
    for r in results:
        path = Path(truth_dir) / f"layer_{r.layer:03d}.ply"
        if not path.exists():
            continue
        fields, faces = read_mesh_ply(path)
        truth_O = np.column_stack([fields[k] for k in "xyz"]).astype(np.float64)
        yield (r, truth_O, faces, truth_O[:, :2].min(axis=0) + CROP_MM,
               truth_O[:, :2].max(axis=0) - CROP_MM)


def truth_height_at(xy_O, h, x0, y0, cell) -> np.ndarray:
    """Bilinear height [mm] (n,) of the grid heights ``h`` (H, W) (vertex (i, j) at
    (x0 + i cell, y0 + j cell)) at ``xy_O`` (n, 2) [mm]; clamped at the grid's border."""
    xy = np.asarray(xy_O, dtype=np.float64).reshape(-1, 2)
    H, W = h.shape
    fx = np.clip((xy[:, 0] - x0) / cell, 0.0, W - 1.0)
    fy = np.clip((xy[:, 1] - y0) / cell, 0.0, H - 1.0)
    i0 = np.minimum(np.floor(fx).astype(np.int64), W - 2)
    j0 = np.minimum(np.floor(fy).astype(np.int64), H - 2)
    tx, ty = fx - i0, fy - j0
    return ((1 - ty) * ((1 - tx) * h[j0, i0] + tx * h[j0, i0 + 1])
            + ty * ((1 - tx) * h[j0 + 1, i0] + tx * h[j0 + 1, i0 + 1]))


def _drift(offsets: dict[int, tuple], sign: int, tolerance_mm: float) -> dict:
    """A track's drift figures from its per-layer true offsets ``{layer: (offset_mm (k,), area
    (k,))}`` (true surface minus the reference the run used, at its flagged vertices)."""
    share, median = {}, {}
    for k, (off, w) in sorted(offsets.items()):
        total = float(np.sum(w))
        share[k] = float(np.sum(w[sign * off >= tolerance_mm]) / total) if total > 0 else 0.0
        median[k] = float(np.median(off))
    since = next((k for k, v in share.items() if v >= DRIFT_SHARE), None)
    rate = None
    if since is not None:
        ks = np.array([k for k in median if k >= since], np.float64)
        if ks.size >= 2 and np.ptp(ks) > 0:
            rate = float(np.polyfit(ks, [median[int(k)] for k in ks], 1)[0])
    return {"drift_share_by_layer": {str(k): v for k, v in share.items()},
            "true_offset_median_by_layer_mm": {str(k): v for k, v in median.items()},
            "drift_share": max(share.values(), default=0.0), "drift_since_layer": since,
            "drift_rate_mm_per_layer": rate, "drift_tolerance_mm": float(tolerance_mm)}


def truth_checks(results, truth_dir: Path,
                 tolerance_mm: float | None = None) -> tuple[dict[int, dict], dict[int, dict]]:
    """The reconstruction per layer and each track's flagged vertices, against the true surface.

    The truth is the twin's ``layer_NNN.ply`` (the true top surface when the layer closed);
    only observed vertices inside its xy extent (less ``CROP_MM``) are compared, as the truth
    mesh is cropped to the built region. Each layer's truth is read once and searched once;
    a track's flagged vertices are among the compared ones. The truth is read as plain arrays
    (a loaded ``trimesh.Trimesh`` sits in reference cycles until the garbage collector runs:
    over the 124 layers of the twisted tower that held 690 MiB of truth meshes at the run's
    memory peak).

    Returns
    -------
    layers : ``{layer: {"rms_mm", "p95_mm", "n_vertices"}}``, the unsigned distance [mm] of the
        observed reconstructed vertices from the true surface
    tracks : ``{track id: {"n_vertices", "deviation_median_mm" (signed, from the reference),
        "truth_distance_median_mm", "truth_distance_p90_mm" (unsigned, from the true surface),
        "part_deviates"}}`` over all the track's layers; ``part_deviates``: the median distance
        from the truth is under ``PART_DEVIATES_SHARE`` of the median |deviation|, so the true
        part itself stands off the reference there, as measured. A track that no fault explains
        but whose part deviates reports the twin's part as it is (the monitor's model differs
        from the twin's physics there), not a measurement error.
        With ``tolerance_mm`` (the run's event tolerance, ``[monitor] delta_global_mm``) and a
        grid truth, also the reference the run used against the true surface at the track's
        flagged vertices (true height minus reference height at their xy, per layer):
        ``drift_share_by_layer`` (the area share where the truth stands off the reference by
        at least the tolerance in the track's sign, the sign of its median deviation),
        ``true_offset_median_by_layer_mm``, ``drift_share`` (the largest), ``drift_since_layer``
        (the first layer where the share reaches ``DRIFT_SHARE``), ``drift_rate_mm_per_layer``
        (the least-squares slope of the median offset from that layer on; None with one layer).
    """
    unobserved = CLASS_NAMES.index("unobserved")
    layers: dict[int, dict] = {}
    dev_by: dict[int, list] = {}
    dist_by: dict[int, list] = {}
    off_by: dict[int, dict] = {}
    for r, truth_O, faces, lo, hi in _truth_layers(results, truth_dir):
        dev = r.deviation
        xy = dev.vertices_O[:, :2]
        ids = np.flatnonzero((dev.class_code != unobserved)
                             & np.all((xy >= lo) & (xy <= hi), axis=1))
        if ids.size == 0:
            continue
        d = mesh_distance(dev.vertices_O[ids], truth_O, faces)
        layers[int(r.layer)] = {"rms_mm": float(np.sqrt(np.mean(d ** 2))),
                                "p95_mm": float(np.percentile(d, 95)),
                                "n_vertices": int(ids.size)}
        dist_at = np.full(dev.vertices_O.shape[0], np.nan)
        dist_at[ids] = d
        grid = grid_of_mesh(truth_O, faces) if tolerance_mm is not None else None
        areas = dev.vertex_areas() if grid is not None else None
        for reg, tid in zip(r.regions, r.track_ids, strict=True):
            if tid is None:
                continue
            rid = np.asarray(reg.vertex_ids, dtype=np.int64)
            rid = rid[np.isfinite(dist_at[rid])]
            if rid.size:
                dev_by.setdefault(int(tid), []).append(dev.signed_distance_mm[rid])
                dist_by.setdefault(int(tid), []).append(dist_at[rid])
                if grid is not None:
                    xy_r = dev.vertices_O[rid, :2]
                    off = truth_height_at(xy_r, *grid) - r.reference.height_at(xy_r)
                    prev = off_by.setdefault(int(tid), {}).get(int(r.layer))
                    new = (off, areas[rid])
                    off_by[int(tid)][int(r.layer)] = new if prev is None else (
                        np.concatenate([prev[0], off]), np.concatenate([prev[1], areas[rid]]))
    tracks = {}
    for tid, devs in dev_by.items():
        dv, e = np.concatenate(devs), np.concatenate(dist_by[tid])
        med_dev, med_dist = float(np.median(dv)), float(np.median(e))
        tracks[tid] = {"n_vertices": int(dv.size), "deviation_median_mm": med_dev,
                       "truth_distance_median_mm": med_dist,
                       "truth_distance_p90_mm": float(np.percentile(e, 90)),
                       "part_deviates": med_dist < PART_DEVIATES_SHARE * abs(med_dev)}
        if tid in off_by:
            tracks[tid].update(_drift(off_by[tid], 1 if med_dev >= 0 else -1, tolerance_mm))
    return layers, tracks
