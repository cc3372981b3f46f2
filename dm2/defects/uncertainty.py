"""Per-vertex uncertainty of the signed deviation: measurement and reference model error.

A deviation is evidence of a defect only where it exceeds what the measurement and the model
can explain. Each measured vertex gets a standard deviation [mm], the error sources combined in
quadrature, ``sigma^2 = features @ coefficients`` with

=========  ===========================================  ======================================
feature    value per vertex                             coefficient (``[monitor.uncertainty]``)
=========  ===========================================  ======================================
floor      1                                            ``floor_mm^2``: reconstruction
                                                        (voxelisation, meshing, pose) and
                                                        reference floor everywhere
range      ``1 / max(weight, 1)``                       ``range_mm^2``: one observation's
                                                        range noise, averaged over the TSDF
                                                        weight (observation count)
wall       ``(1 - |n_z|)^2`` of the measured normal     ``wall_mm^2``: grazing incidence on
                                                        walls and the Gaussian model's known
                                                        mismatch at walls
edge       ``min(1, max(0, |H_ref| - 1 / R) *       ``edge_mm^2``: rounded edges and
           EDGE_RADIUS_MM)^2``, ``R`` the local         corners of the reference (a gentle
           curvature radius of dm2.defects.classify     undulation is no edge)
foot       ``(min(1, rise / FOOT_RISE_MM) * low)^2``,   ``foot_mm^2``: the foot of a wall,
           ``rise`` = how far the reference rises       where the profilers see poorly and
           within ``FOOT_RADIUS_MM``, ``low`` =         the plume's tail meets the plate
           ``max(0, 1 - h_ref / FOOT_BAND_MM)`` (near
           the plate)
gap        ``min(gap, GAP_CAP_MM)^2``, the distance     ``gap_mm_per_mm^2``: surface filled
           [mm] to the nearest well observed vertex     in between observations
           (weight >= ``WELL_OBSERVED_WEIGHT``; 0
           where the layer has none)
height     ``(h_ref / HEIGHT_SCALE_MM)^2``, the         ``height_mm^2``: the reference's error
           reference height at the vertex               accumulates with the deposited height
                                                        (layers the model has run open-loop)
plume      ``(sigma^2 laplacian(h_ref))^2``, how far    ``plume_rel^2``: the plume width is
           the reference moves per relative change of   known only to a fraction (a half
           its plume width                              angle of 6 instead of 5 deg: +9 %);
           (:meth:`ReferenceMap.plume_sensitivity_at`)  edges, wall feet and corners move
                                                        with it, flat tops do not
=========  ===========================================  ======================================

A vertex is called over- or underbuilt only where ``|d| > delta_global_mm`` and
``|d| > confidence_k * sigma`` (:mod:`dm2.defects.classify`); flagged deviations inside the
bound are ``uncertain`` (local over/underbuild keeps the paper's rule; it is an early warning
that opens no track on its own).
The coefficients can be refitted from a fault-free run of one's own cell with
:func:`dm2.defects.uncertainty_fit.fit_uncertainty`; each layer raises the model-error terms
(wall, edge, foot, plume) to what its own deviations show (:mod:`dm2.defects.uncertainty_online`).

Not modelled: the growth of the reference error with the layers since a region was last
observed (the TSDF keeps no observation time per voxel).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter
from scipy.spatial import cKDTree

from dm2.defects.classify import LOCAL_CURVATURE_RADIUS_MM
from dm2.reference.height_map import bilinear_height

FEATURES = ("floor", "range", "wall", "edge", "foot", "gap", "height", "plume")
EDGE_RADIUS_MM = 2.0  # curvature 1/2 mm^-1 beyond the local radius's counts as a full edge
FOOT_RADIUS_MM = 2.0  # the reference rising within this radius marks the foot of a wall
FOOT_RISE_MM = 1.0  # ... by this much or more: full foot weight
FOOT_BAND_MM = 1.0  # the foot is within this height of the plate (z_O = 0)
WELL_OBSERVED_WEIGHT = 2.0  # TSDF weight of a vertex counted as well observed for the gap
GAP_CAP_MM = 5.0
HEIGHT_SCALE_MM = 10.0  # height_mm is the reference's error after 10 mm of deposit


def coefficients(ucfg) -> np.ndarray:
    """Variance coefficients [mm^2] (8,) in :data:`FEATURES` order from an UncertaintyConfig."""
    return np.array([ucfg.floor_mm, ucfg.range_mm, ucfg.wall_mm, ucfg.edge_mm, ucfg.foot_mm,
                     ucfg.gap_mm_per_mm, ucfg.height_mm, ucfg.plume_rel], np.float64) ** 2


def foot_rise_map(heights_mm: np.ndarray, cell_mm: float) -> np.ndarray:
    """How far the reference rises within :data:`FOOT_RADIUS_MM` of each cell [mm] (ny, nx)."""
    size = 2 * max(int(round(FOOT_RADIUS_MM / cell_mm)), 1) + 1
    return maximum_filter(heights_mm, size=size, mode="nearest") - heights_mm


def gap_distance_mm(vertices_O: np.ndarray, weight: np.ndarray, min_weight: float) -> np.ndarray:
    """Distance [mm] (n,) from each vertex to the nearest well observed one (0 for those)."""
    w = np.asarray(weight, np.float64)
    well = w >= max(WELL_OBSERVED_WEIGHT, min_weight)
    gap = np.zeros(len(w))
    poor = np.flatnonzero(~well)
    if poor.size == 0 or not well.any():  # nothing to measure the distance from
        return gap
    tree = cKDTree(vertices_O[well])
    dist, _ = tree.query(vertices_O[poor], distance_upper_bound=GAP_CAP_MM)
    gap[poor] = np.minimum(dist, GAP_CAP_MM)
    return gap


def uncertainty_features(vertices_O, weight, normals_O, foot_O, reference,
                         reference_curvature, min_weight: float) -> np.ndarray:
    """The (n, 8) feature matrix of :data:`FEATURES` (see the module docstring).

    Parameters
    ----------
    vertices_O : (n, 3) [mm]; weight : (n,) TSDF weight; normals_O : (n, 3) unit normals
    foot_O : (n, 3) [mm], closest reference point of each vertex
    reference : ReferenceMap the deviation was measured against
    reference_curvature : (n,) [1/mm], the reference's mean curvature at ``foot_O``
    min_weight : the monitor's ``min_weight``
    """
    v = np.asarray(vertices_O, np.float64)
    n = len(v)
    w = np.asarray(weight, np.float64)
    f = np.empty((n, len(FEATURES)))
    f[:, 0] = 1.0
    f[:, 1] = 1.0 / np.maximum(np.where(np.isfinite(w), w, 1e9), 1.0)
    nz = np.abs(np.asarray(normals_O, np.float64)[:, 2]) if n else np.zeros(0)
    f[:, 2] = (1.0 - np.clip(nz, 0.0, 1.0)) ** 2
    excess = np.maximum(np.abs(reference_curvature) - 1.0 / LOCAL_CURVATURE_RADIUS_MM, 0.0)
    f[:, 3] = np.minimum(1.0, excess * EDGE_RADIUS_MM) ** 2
    foot = np.asarray(foot_O, np.float64).reshape(-1, 3)
    rise = bilinear_height(foot_rise_map(reference.heights_mm, reference.cell_mm),
                           reference.cell_mm, foot[:, :2]) if n else np.zeros(0)
    low = np.clip(1.0 - foot[:, 2] / FOOT_BAND_MM, 0.0, 1.0)
    f[:, 4] = (np.minimum(1.0, np.maximum(rise, 0.0) / FOOT_RISE_MM) * low) ** 2
    f[:, 5] = gap_distance_mm(v, np.where(np.isfinite(w), w, 1e9), min_weight) ** 2
    f[:, 6] = (np.maximum(foot[:, 2], 0.0) / HEIGHT_SCALE_MM) ** 2
    f[:, 7] = reference.plume_sensitivity_at(foot[:, :2]) ** 2 if n else 0.0
    return f


def vertex_sigma_mm(features: np.ndarray, ucfg) -> np.ndarray:
    """Combined standard deviation [mm] (n,) of each vertex's deviation."""
    return np.sqrt(np.maximum(features @ coefficients(ucfg), 0.0))
