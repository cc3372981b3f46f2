"""Continuous (C3D-style) toolpath generation from a watertight part mesh.

Per layer ``k`` (sprayed onto ``z_O = k * layer_mm``, region = the mesh's section at the
layer's mid-height):

* **infill** - raster lines at ``line_spacing_mm`` clipped to the region, linked boustrophedon
  into chains; raster direction ``infill_angle_deg`` + 90 degrees on every other layer
  (``single``) or every other double layer (``double``); spray axis straight down;
* **edge** - the region's rings inset by ``contour_inset_mm`` (default half a spacing), the
  spray axis tilted by ``contour_angle_deg``. With ``contour_jet = "toward_wall"`` the nozzle
  leans outward and the jet meets the wall from outside,
  ``a_O = normalize(-cos(alpha) e_z - sin(alpha) n_out)``: a wall sloping at ``beta`` takes it
  at ``beta - alpha`` and is built up straight, as the paper tilts the nozzle "to minimize
  tapering". With ``"away_from_wall"`` (the default, which the shipped small scenarios and the
  near-net reference are tuned to) ``a_O = normalize(-cos(alpha) e_z + sin(alpha) n_out)``:
  the wall takes the jet at ``beta + alpha``, most of it rebounds and tall parts taper;
* **overhang** - infill and edge moves whose outline lies more than ``overhang_min_mm`` beyond
  the layer below; slower speed, spray axis straight down;
* **skip** - fast moves joining pieces that cannot be linked inside the region (powder keeps
  flowing, so ``spray_on`` is True); routed along the contour rings instead of across holes.

Strategies: ``single`` = infill then one contour per layer. ``double`` = infill of layer k,
infill of layer k+1 (the reverse pass, starting where the first ended, same raster direction),
then the contours of both layers' outlines, labelled layer k+1 (they come after its infill).

Corners of every spraying chain are rounded like a robot zone of ``zone_mm`` (the arc leaves
the path ``zone_mm`` before the corner and rejoins it ``zone_mm`` after); spraying moves
are split so no move is longer than the line spacing. The point ``i`` carries the kind, speed
and spray state of the move *into* it; a skip's arrival point already carries the axis of the
stroke it leads into.
"""

from __future__ import annotations

import logging

import numpy as np
import trimesh

from dm2.core.config import ToolpathConfig
from dm2.core.messages import KIND_CODE, TOOLPATH_KINDS, Toolpath
from dm2.core.tolerances import DIVISOR_FLOOR
from dm2.toolpath.contours import contour_loops, corner_angles_deg, open_loop_near
from dm2.toolpath.infill import raster_segments
from dm2.toolpath.linking import DOWN_O, PathBuilder, Region, order_raster
from dm2.toolpath.overhang import classify_overhang, overhang_regions
from dm2.toolpath.polyline import densify, drop_repeats, fillet, right_normals_closed
from dm2.toolpath.slicing import SlicedPart, slice_mesh

log = logging.getLogger(__name__)

CORNER_MIN_TURN_DEG = 10.0  # contour vertices turning more than this are listed as corners


class _Planner:
    def __init__(self, sliced: SlicedPart, cfg: ToolpathConfig):
        self.cfg = cfg
        self.sliced = sliced
        self.spacing = cfg.line_spacing_mm
        self.inset = cfg.contour_inset_mm if cfg.contour_inset_mm is not None \
            else cfg.line_spacing_mm / 2
        self.alpha = np.radians(cfg.contour_angle_deg)
        self.jet_out = -1.0 if cfg.contour_jet == "toward_wall" else 1.0  # sign on n_out
        self.loops = [contour_loops(r, self.inset) for r in sliced.regions]
        self.regions = [Region(r, lp) for r, lp in zip(sliced.regions, self.loops, strict=True)]
        self.overhang = overhang_regions(sliced.regions, cfg.overhang_min_mm)
        self.builder = PathBuilder()
        self.corner_index: list[int] = []
        self.corner_angle_deg: list[float] = []

    def infill(self, j: int, layer: int, z_mm: float, angle_rad: float) -> None:
        region = self.regions[j]
        segs, scanline = raster_segments(region.polygon, angle_rad, self.spacing)
        start = self.builder.pos_xy if self.builder.pos_xy is not None else np.zeros(2)
        for chain in order_raster(segs, scanline, start, region, self.spacing):
            xy, _ = densify(fillet(chain, self.cfg.zone_mm)[0], self.spacing)
            kind = np.full(len(xy) - 1, KIND_CODE["infill"], dtype=np.int8)
            kind = classify_overhang(xy, kind, self.overhang[j])
            self.builder.move_to(xy[0], region, layer, z_mm, DOWN_O, KIND_CODE["infill"])
            self.builder.spray(xy[1:], DOWN_O, kind, layer, z_mm)

    def contour(self, j: int, layer: int, z_mm: float) -> None:
        region_j = self.regions[j]
        loops = list(self.loops[j])
        zone = self.cfg.zone_mm
        while loops:
            pos = self.builder.pos_xy if self.builder.pos_xy is not None else np.zeros(2)
            dist = [np.min(np.linalg.norm(lp - pos, axis=1)) for lp in loops]
            loop = drop_repeats(open_loop_near(loops.pop(int(np.argmin(dist))), pos,
                                               max(2 * zone, 0.1)))
            rounded, src = fillet(loop, zone)
            xy, seg_end = densify(rounded, self.spacing)
            n_out = right_normals_closed(xy)
            axis = np.column_stack([self.jet_out * np.sin(self.alpha) * n_out,
                                    np.full(len(xy), -np.cos(self.alpha))])
            mid_normal = n_out[1:] + n_out[:-1]
            mid_normal /= np.maximum(np.linalg.norm(mid_normal, axis=1), DIVISOR_FLOOR)[:, None]
            kind = np.full(len(xy) - 1, KIND_CODE["edge"], dtype=np.int8)
            kind = classify_overhang(xy, kind, self.overhang[j],
                                     probe_offset_xy=mid_normal * max(self.inset - 0.01, 0))
            axis[1:][kind == KIND_CODE["overhang"]] = DOWN_O
            first_axis = axis[1] if len(axis) > 1 else axis[0]
            self.builder.move_to(xy[0], region_j, layer, z_mm, first_axis, KIND_CODE["edge"])
            base = self.builder.n_points - 1  # index of xy[0] in the toolpath
            self.builder.spray(xy[1:], axis[1:], kind, layer, z_mm)
            self._record_corners(loop, src, seg_end, base)

    def _record_corners(self, loop, src, seg_end, base) -> None:
        angles = corner_angles_deg(loop)
        for v in np.flatnonzero(np.abs(180.0 - angles) >= CORNER_MIN_TURN_DEG):
            arc = np.flatnonzero(src == v)
            if len(arc) == 0:
                continue
            q = int(arc[len(arc) // 2])
            local = int(np.searchsorted(seg_end, q, side="right") - 1)
            self.corner_index.append(base + local)
            self.corner_angle_deg.append(float(angles[v]))


def generate_toolpath(mesh_O: trimesh.Trimesh, cfg: ToolpathConfig) -> Toolpath:
    """Plan the continuous toolpath of a part.

    Parameters
    ----------
    mesh_O : watertight trimesh in the work-object frame O [mm], base at z = 0
    cfg : dm2.core.config.ToolpathConfig

    Returns
    -------
    Toolpath
        One continuous path; ``meta`` holds ``layer_z_mm`` (list, [mm]), ``n_layers``,
        ``strategy``, ``line_spacing_mm`` and ``corners`` = {"index": toolpath indices of the
        apex of each rounded contour corner, "angle_deg": its interior angle (material side)}.
    """
    sliced = slice_mesh(mesh_O, cfg.layer_mm, cfg.max_layers)
    plan = _Planner(sliced, cfg)
    z = sliced.layer_z_mm()
    n = sliced.n_layers
    base = np.radians(cfg.infill_angle_deg)
    quarter = np.pi / 2
    if cfg.strategy == "single":
        for k in range(n):
            plan.infill(k, k, z[k], base + quarter * (k % 2))
            plan.contour(k, k, z[k])
    else:
        for d, k in enumerate(range(0, n, 2)):
            angle = base + quarter * (d % 2)
            top = min(k + 1, n - 1)
            plan.infill(k, k, z[k], angle)
            if k + 1 < n:
                plan.infill(k + 1, k + 1, z[k + 1], angle)
            plan.contour(k, top, z[top])
            if k + 1 < n:
                plan.contour(k + 1, top, z[top])
    rows = plan.builder.arrays()
    speeds = np.array([getattr(cfg.speed_mm_s, name) for name in TOOLPATH_KINDS])
    n_pts = len(rows["kind"])
    meta = {
        "layer_z_mm": [float(v) for v in z],
        "n_layers": int(n),
        "strategy": cfg.strategy,
        "line_spacing_mm": float(cfg.line_spacing_mm),
        "corners": {"index": plan.corner_index, "angle_deg": plan.corner_angle_deg},
    }
    tp = Toolpath(position_O=rows["position_O"], axis_O=rows["axis_O"],
                  speed_mm_s=speeds[rows["kind"]], kind=rows["kind"], layer=rows["layer"],
                  spray_on=np.ones(n_pts, dtype=bool), zone_mm=np.full(n_pts, cfg.zone_mm),
                  meta=meta)
    log.info("toolpath: %d layers, %d points (%s)", n, n_pts, ", ".join(
        f"{name} {int(np.sum(tp.kind == c))}" for c, name in enumerate(TOOLPATH_KINDS)))
    return tp
