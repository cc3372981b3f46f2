"""Signed deviation of a measured surface mesh from the near-net reference (paper sec. 6.2).

The distance is the closest distance of each measured vertex to the reference surface (Open3D
``RaycastingScene`` over the reference's triangulated height map, cropped to the measured part).
Its sign comes from the side of the reference height map the vertex lies on (above: positive =
more material than the reference), never from inside/outside of an open mesh.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from dm2.classify import classify_vertices
from dm2.refmap import ReferenceMap

log = logging.getLogger(__name__)

CROP_MARGIN_MM = 8.0  # reference kept this far around the measured vertices (xy)


def _surface_arrays(surface):
    """``(vertices_O, faces, weight)`` of a dm2.surface.SurfaceMesh-like object, validated."""
    v = np.ascontiguousarray(surface.vertices_O, dtype=np.float64)
    f = np.ascontiguousarray(surface.faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"surface.vertices_O: expected (n, 3), got {v.shape}")
    if f.size and (f.ndim != 2 or f.shape[1] != 3 or f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"surface.faces: expected (m, 3) indices into {len(v)} vertices")
    f = f.reshape(-1, 3)
    w = getattr(surface, "weight", None)
    w = np.full(len(v), np.inf) if w is None else np.asarray(w, dtype=np.float64).reshape(-1)
    if w.shape[0] != v.shape[0]:
        raise ValueError(f"surface.weight: expected ({len(v)},), got {w.shape}")
    return v, f, w


def closest_on_reference(points_O: np.ndarray, reference: ReferenceMap):
    """Signed closest distance [mm] (n,) and closest reference points ``foot_O`` (n, 3)."""
    import open3d as o3d

    p = np.asarray(points_O, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros(0), np.zeros((0, 3))
    rows, cols = reference.crop_indices(p[:, :2].min(0), p[:, :2].max(0), CROP_MARGIN_MM)
    verts, faces = reference.mesh_arrays(rows, cols)
    origin = verts.mean(axis=0)  # float32 queries relative to a local origin keep precision
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((verts - origin).astype(np.float32)),
                        o3d.core.Tensor(faces.astype(np.uint32)))
    q = o3d.core.Tensor((p - origin).astype(np.float32))
    foot = scene.compute_closest_points(q)["points"].numpy().astype(np.float64) + origin
    dist = np.linalg.norm(p - foot, axis=1)
    side = np.sign(p[:, 2] - reference.height_at(p[:, :2]))
    return dist * side, foot


def signed_deviation(surface, reference: ReferenceMap) -> np.ndarray:
    """Per-vertex signed distance [mm] (n,) of ``surface`` to ``reference``.

    Parameters
    ----------
    surface : object with ``vertices_O`` (n, 3) [mm] (e.g. dm2.surface.SurfaceMesh)
    reference : ReferenceMap, the near-net reference of the same layer / time

    Returns
    -------
    (n,) float64 [mm], positive where the part is above the reference (overbuild).
    """
    d, _ = closest_on_reference(np.asarray(surface.vertices_O, dtype=np.float64), reference)
    return d


@dataclass(frozen=True)
class LayerDeviation:
    """Deviation map of one layer (or one moment) and its per-vertex classes.

    Attributes
    ----------
    layer : int
    vertices_O : (n, 3) float64 [mm], measured surface vertices
    faces : (m, 3) int64, triangles
    weight : (n,) float64, fusion weight per vertex (observation confidence)
    signed_distance_mm : (n,) float64 [mm], + above the reference
    foot_O : (n, 3) float64 [mm], closest point on the reference per vertex
    class_code : (n,) int8, codes of dm2.classify.CLASS_NAMES
    local_metric : (n,) float64, normalised curvature-weighted deviation (dimensionless)
    mean_curvature : (n,) float64 [1/mm], + convex
    stamp_s : float [s]
    """

    layer: int
    vertices_O: np.ndarray
    faces: np.ndarray
    weight: np.ndarray
    signed_distance_mm: np.ndarray
    foot_O: np.ndarray
    class_code: np.ndarray
    local_metric: np.ndarray
    mean_curvature: np.ndarray
    stamp_s: float = 0.0

    @property
    def n_vertices(self) -> int:
        return int(self.vertices_O.shape[0])

    def vertex_areas(self) -> np.ndarray:
        """One third of the area of every incident triangle, per vertex [mm^2] (n,)."""
        return vertex_areas(self.vertices_O, self.faces)


def vertex_areas(vertices_O: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Barycentric vertex areas [mm^2] (n,): a third of each incident triangle."""
    if len(faces) == 0:
        return np.zeros(len(vertices_O))
    tri = vertices_O[faces]
    fa = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return np.bincount(faces.ravel(), np.repeat(fa / 3.0, 3), minlength=len(vertices_O))


def layer_deviation(surface, reference: ReferenceMap, monitor_cfg, layer: int | None = None,
                    stamp_s: float | None = None) -> LayerDeviation:
    """Signed deviation and classification of a measured surface against a reference.

    ``monitor_cfg`` supplies ``delta_global_mm``, ``delta_local`` and ``min_weight``.
    """
    v, f, w = _surface_arrays(surface)
    d, foot = closest_on_reference(v, reference)
    classes = classify_vertices(v, f, w, d, monitor_cfg)
    layer = reference.layer if layer is None else int(layer)
    log.debug("layer %d: %d vertices, deviation %.3f..%.3f mm", layer, len(v),
              float(d.min()) if len(d) else 0.0, float(d.max()) if len(d) else 0.0)
    return LayerDeviation(layer, v, f, w, d, foot, classes.class_code, classes.local_metric,
                          classes.mean_curvature,
                          float(reference.stamp_s if stamp_s is None else stamp_s))
