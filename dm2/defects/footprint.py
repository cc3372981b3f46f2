"""The part's planned footprint on the plate, and overspray outside it.

Cold spray deposits a thin skirt of powder around the part (the plume's tail, skip moves).
Deviations on the plate at least ``overspray_margin_mm`` outside the planned outline are class
``overspray``: reported, never tracked, unless they are joined (same sign, over mesh edges) to
a confident defect closer to the part, which then keeps its class all the way out (a fault at
a wall stays a defect).

The planned outline is the union over all layers of the toolpath's depositing moves (infill,
edge, overhang; not skip moves) widened by half a bead (``BEAD_HALF_WIDTH_MM``, half the
default line spacing), rasterised on a grid over the plate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.ndimage import binary_dilation, distance_transform_edt
from scipy.sparse.csgraph import connected_components

from dm2.core.messages import KIND_CODE
from dm2.defects.classify import DEFECT_CLASSES, OVERSPRAY, UNCERTAIN
from dm2.reference.height_map import bilinear_height

BEAD_HALF_WIDTH_MM = 1.0
SAMPLE_MM = 0.25  # path sampling step when rasterising the outline


@dataclass(frozen=True)
class PlannedOutline:
    """Distance [mm] outside the planned footprint on a cell-centred grid over the plate.

    Attributes
    ----------
    outside_mm : (ny, nx) float64 [mm], 0 inside the footprint
    cell_mm : float [mm]
    """

    outside_mm: np.ndarray
    cell_mm: float

    @classmethod
    def from_toolpath(cls, toolpath, size_mm=(120.0, 120.0), cell_mm: float = 0.5,
                      bead_half_width_mm: float = BEAD_HALF_WIDTH_MM) -> PlannedOutline | None:
        """The footprint of ``toolpath``'s depositing moves; None if it has none."""
        pos = np.asarray(toolpath.position_O, np.float64)
        kind = np.asarray(toolpath.kind)
        dep = (kind != KIND_CODE["skip"]) & np.asarray(toolpath.spray_on, bool)
        seg = np.flatnonzero(dep[1:] & (np.asarray(toolpath.layer)[1:]
                                        == np.asarray(toolpath.layer)[:-1])) + 1
        if seg.size == 0:
            return None
        a, b = pos[seg - 1, :2], pos[seg, :2]
        steps = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / SAMPLE_MM), 1).astype(int)
        rep = np.repeat(np.arange(len(seg)), steps + 1)
        # np.linspace(0, 1, s + 1) of every segment at once: k * (1 / s), the last exactly 1
        k = np.arange(len(rep)) - np.repeat(np.cumsum(steps + 1) - (steps + 1), steps + 1)
        t = k * (1.0 / steps)[rep]
        t[np.cumsum(steps + 1) - 1] = 1.0
        pts = a[rep] + t[:, None] * (b - a)[rep]
        nx = max(int(round(size_mm[0] / cell_mm)), 2)
        ny = max(int(round(size_mm[1] / cell_mm)), 2)
        i = np.clip(np.floor(pts[:, 0] / cell_mm).astype(int), 0, nx - 1)
        j = np.clip(np.floor(pts[:, 1] / cell_mm).astype(int), 0, ny - 1)
        mask = np.zeros((ny, nx), bool)
        mask[j, i] = True
        r = max(int(round(bead_half_width_mm / cell_mm)), 0)
        if r:
            yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
            mask = binary_dilation(mask, xx * xx + yy * yy <= r * r)
        return cls(distance_transform_edt(~mask) * cell_mm, float(cell_mm))

    def outside_at(self, xy_O) -> np.ndarray:
        """Distance [mm] (n,) outside the footprint at ``xy_O`` (n, 2), 0 inside."""
        return bilinear_height(self.outside_mm, self.cell_mm, xy_O)


def mark_overspray(code: np.ndarray, signed_distance_mm: np.ndarray, faces: np.ndarray,
                   outside_mm: np.ndarray, margin_mm: float) -> np.ndarray:
    """Class codes with overspray marked (a copy; see the module docstring).

    Flagged vertices (defect or uncertain) at least ``margin_mm`` outside the footprint become
    ``overspray`` unless their same-signed flagged component holds a defect vertex nearer the
    part than ``margin_mm``.
    """
    code = np.array(code, copy=True)
    flagged = np.isin(code, (*DEFECT_CLASSES, UNCERTAIN))
    out = flagged & (np.asarray(outside_mm) >= margin_mm)
    if not out.any():
        return code
    n = len(code)
    sign = np.sign(signed_distance_mm)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    keep = flagged[e[:, 0]] & flagged[e[:, 1]] & (sign[e[:, 0]] == sign[e[:, 1]])
    e = e[keep]
    graph = sparse.coo_matrix((np.ones(len(e), np.int8), (e[:, 0], e[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    anchored = np.zeros(labels.max() + 1, bool)
    anchor = np.isin(code, DEFECT_CLASSES) & ~out
    anchored[labels[anchor]] = True
    code[out & ~anchored[labels]] = OVERSPRAY
    return code
