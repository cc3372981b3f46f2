"""Part geometries for scenarios: watertight meshes in the work-object frame O.

Every part is centred on the plate (``plate_size_mm = (Lx, Ly, thickness)``) with its base on
the plate's top surface (z_O = 0). Parameters come from ``[part] params`` (all in mm / deg);
an unknown parameter is a :class:`~dm2.core.config.ConfigError` naming ``part.params.<name>``.

Generators
----------
``box``           width_mm (x), depth_mm (y), height_mm; default 40 x 30 x 8.
``pad``           a small rectangular pad for fast tests; default 20 x 10 x 4.
``twisted_tower`` the paper's twisted tower: a rounded square (width_mm 50, corner_radius_mm 8)
                  lofted to height_mm 99.2 (62 double layers of 0.8 mm) while it twists by
                  twist_deg 90; it narrows smoothly to waist_scale 0.6 at 55 % of the height,
                  then expands (cubically, steepest at the top) to top_scale 1.1, an overhang.
``seven_sided``   a hollow seven-sided prism whose corner angles (interior, counter-clockwise
                  from the acute one) are 45, 220, 60, 150, 120, 90 and 215 degrees (sum 900;
                  the two reflex corners make the 45..150 degree set closable); size_mm 70 is
                  its largest extent, wall_mm 13 the wall width around the hollow centre
                  (a mitred inset of the outline), height_mm 24.
``cylinder``      a round pad: diameter_mm 30, height_mm 2.4.
``ring``          an annulus: outer_diameter_mm 36, inner_diameter_mm 16, height_mm 2.4.
``tee``           a T: a bar span_mm 30 long and width_mm 10 wide (along x), with a stem of
                  the same width standing stem_mm 10 out of its middle (along +y); height_mm
                  2.4.
``triangle``      an isosceles triangle: base_mm 36 (along x), depth_mm 28 from the base to the
                  apex (along +y), height_mm 2.4.
``stl``           ``[part] stl = "file.stl"``: a watertight mesh, re-centred on the plate with
                  its lowest point on the plate.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import shapely
import trimesh
from shapely.geometry import Polygon

from dm2.core.config import ConfigError, PartConfig

SEVEN_SIDED_ANGLES_DEG = (45.0, 220.0, 60.0, 150.0, 120.0, 90.0, 215.0)

DEFAULTS: dict[str, dict[str, float]] = {
    "box": {"width_mm": 40.0, "depth_mm": 30.0, "height_mm": 8.0},
    "pad": {"width_mm": 20.0, "depth_mm": 10.0, "height_mm": 4.0},
    "twisted_tower": {"height_mm": 99.2, "width_mm": 50.0, "corner_radius_mm": 8.0,
                      "twist_deg": 90.0, "waist_scale": 0.6, "waist_at": 0.55,
                      "top_scale": 1.1},
    "seven_sided": {"height_mm": 24.0, "size_mm": 70.0, "wall_mm": 13.0},
    "cylinder": {"diameter_mm": 30.0, "height_mm": 2.4},
    "ring": {"outer_diameter_mm": 36.0, "inner_diameter_mm": 16.0, "height_mm": 2.4},
    "tee": {"span_mm": 30.0, "width_mm": 10.0, "stem_mm": 10.0, "height_mm": 2.4},
    "triangle": {"base_mm": 36.0, "depth_mm": 28.0, "height_mm": 2.4},
}
CIRCLE_QUAD_SEGMENTS = 64  # segments per quarter circle of the round parts' outlines


def _params(part: PartConfig) -> dict[str, float]:
    defaults = DEFAULTS[part.generator]
    unknown = sorted(set(part.params) - set(defaults))
    if unknown:
        raise ConfigError(f"part.params.{unknown[0]}: unknown parameter for generator "
                          f"'{part.generator}' (known: {', '.join(sorted(defaults))})")
    values = {**defaults, **{k: float(v) for k, v in part.params.items()}}
    for k, v in values.items():
        if not np.isfinite(v) or (v <= 0 and k != "twist_deg"):
            raise ConfigError(f"part.params.{k}: must be a positive number, got {v}")
    return values


def build_part(part: PartConfig, plate_size_mm) -> trimesh.Trimesh:
    """The part's watertight mesh in O [mm], centred on the plate, base at z = 0.

    Raises
    ------
    ConfigError
        unknown or invalid parameter, unreadable / empty / non-watertight STL, or a part that
        does not fit on the plate
    """
    lx, ly = float(plate_size_mm[0]), float(plate_size_mm[1])
    if part.stl is not None:
        mesh = load_stl(part.stl)
    else:
        p = _params(part)
        builder = {"box": _box, "pad": _box, "twisted_tower": _twisted_tower,
                   "seven_sided": _seven_sided, "cylinder": _cylinder, "ring": _ring,
                   "tee": _tee, "triangle": _triangle}[part.generator]
        mesh = builder(p)
    lo, hi = mesh.bounds
    mesh.apply_translation([lx / 2 - (lo[0] + hi[0]) / 2, ly / 2 - (lo[1] + hi[1]) / 2, -lo[2]])
    ext = mesh.extents
    if ext[0] > lx + 1e-9 or ext[1] > ly + 1e-9:
        src = part.stl or f"generator '{part.generator}'"
        raise ConfigError(f"part ({src}): footprint {ext[0]:.1f} x {ext[1]:.1f} mm does not fit "
                          f"on the {lx:.0f} x {ly:.0f} mm plate")
    return mesh


def load_stl(path: str | Path) -> trimesh.Trimesh:
    """Load a watertight STL; errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: part.stl: file not found")
    try:
        mesh = trimesh.load(str(path), file_type="stl", force="mesh", process=True)
    except Exception as exc:  # trimesh raises many kinds on malformed files
        raise ConfigError(f"{path}: part.stl: cannot read STL: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ConfigError(f"{path}: part.stl: mesh is empty (no triangles)")
    if not mesh.is_watertight:
        raise ConfigError(f"{path}: part.stl: mesh is not watertight (it has open edges), "
                          "so it cannot be sliced into closed layer outlines")
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _box(p: dict[str, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(p["width_mm"], p["depth_mm"], p["height_mm"]))


def _resample_ring(poly: Polygon, n: int) -> np.ndarray:
    ring = poly.exterior
    s = np.linspace(0.0, ring.length, n, endpoint=False)
    return shapely.get_coordinates(shapely.line_interpolate_point(ring, s))


def _tower_scale(t: np.ndarray, p: dict[str, float]) -> np.ndarray:
    waist, at, top = p["waist_scale"], p["waist_at"], p["top_scale"]
    low = 1.0 - (1.0 - waist) * np.sin(np.pi / 2 * np.clip(t / at, 0, 1)) ** 2
    high = waist + (top - waist) * np.clip((t - at) / (1 - at), 0, 1) ** 3
    return np.where(t <= at, low, high)


def _twisted_tower(p: dict[str, float]) -> trimesh.Trimesh:
    if not 0 < p["waist_at"] < 1:
        raise ConfigError("part.params.waist_at: must lie between 0 and 1 (fraction of height)")
    half = p["width_mm"] / 2 - p["corner_radius_mm"]
    if half <= 0:
        raise ConfigError("part.params.corner_radius_mm: must be less than half of width_mm")
    template = _resample_ring(shapely.box(-half, -half, half, half).buffer(
        p["corner_radius_mm"], quad_segs=8), 128)
    height = p["height_mm"]
    n_rings = max(2, int(np.ceil(height / 0.8)) + 1)
    z = np.linspace(0.0, height, n_rings)
    t = z / height
    scale = _tower_scale(t, p)
    twist = np.radians(p["twist_deg"]) * t
    c, s = np.cos(twist), np.sin(twist)
    x = scale[:, None] * (c[:, None] * template[:, 0] - s[:, None] * template[:, 1])
    y = scale[:, None] * (s[:, None] * template[:, 0] + c[:, None] * template[:, 1])
    m = len(template)
    verts = np.column_stack([x.ravel(), y.ravel(), np.repeat(z, m)])
    verts = np.vstack([verts, [0.0, 0.0, 0.0], [0.0, 0.0, height]])
    bottom, top = len(verts) - 2, len(verts) - 1
    ring = np.arange(m)
    nxt = (ring + 1) % m
    faces = []
    for r in range(n_rings - 1):
        a, b = r * m + ring, r * m + nxt
        a2, b2 = a + m, b + m
        faces.append(np.column_stack([a, b, b2]))
        faces.append(np.column_stack([a, b2, a2]))
    faces.append(np.column_stack([np.full(m, bottom), nxt, ring]))
    last = (n_rings - 1) * m
    faces.append(np.column_stack([np.full(m, top), last + ring, last + nxt]))
    mesh = trimesh.Trimesh(verts, np.vstack(faces), process=True)
    trimesh.repair.fix_normals(mesh)
    return mesh


def seven_sided_outline(size_mm: float) -> Polygon:
    """The seven-sided outline (counter-clockwise), largest extent ``size_mm``, in mm.

    Side directions follow from the corner angles; side lengths are the closure-constrained
    least-squares fit to equal sides (closed form), so the polygon closes exactly.
    """
    interior = np.radians(SEVEN_SIDED_ANGLES_DEG)
    turn = np.pi - interior
    heading = np.concatenate([[0.0], np.cumsum(turn[1:])])
    U = np.column_stack([np.cos(heading), np.sin(heading)])
    A = U.T
    ones = np.ones(len(U))
    lengths = ones - A.T @ np.linalg.solve(A @ A.T, A @ ones)
    pts = np.vstack([[0.0, 0.0], np.cumsum(lengths[:, None] * U, axis=0)[:-1]])
    pts *= size_mm / np.ptp(pts, axis=0).max()
    return Polygon(pts)


def _seven_sided(p: dict[str, float]) -> trimesh.Trimesh:
    outline = seven_sided_outline(p["size_mm"])
    hole = outline.buffer(-p["wall_mm"], join_style="mitre", mitre_limit=10.0)
    if hole.is_empty or hole.geom_type != "Polygon" or hole.area < 1.0:
        raise ConfigError(f"part.params.wall_mm: {p['wall_mm']} mm leaves no hollow centre in a "
                          f"{p['size_mm']} mm seven-sided part")
    shape = Polygon(outline.exterior.coords, [hole.exterior.coords])
    return trimesh.creation.extrude_polygon(shape, p["height_mm"])


def _disc(diameter_mm: float):
    return shapely.Point(0.0, 0.0).buffer(diameter_mm / 2, quad_segs=CIRCLE_QUAD_SEGMENTS)


def _cylinder(p: dict[str, float]) -> trimesh.Trimesh:
    return trimesh.creation.extrude_polygon(_disc(p["diameter_mm"]), p["height_mm"])


def _ring(p: dict[str, float]) -> trimesh.Trimesh:
    if p["inner_diameter_mm"] >= p["outer_diameter_mm"]:
        raise ConfigError(f"part.params.inner_diameter_mm: {p['inner_diameter_mm']} mm must be "
                          f"less than outer_diameter_mm {p['outer_diameter_mm']} mm")
    shape = _disc(p["outer_diameter_mm"]).difference(_disc(p["inner_diameter_mm"]))
    return trimesh.creation.extrude_polygon(shape, p["height_mm"])


def _tee(p: dict[str, float]) -> trimesh.Trimesh:
    a, w, st = p["span_mm"] / 2, p["width_mm"] / 2, p["stem_mm"]
    if w >= a:
        raise ConfigError(f"part.params.width_mm: {p['width_mm']} mm leaves no bar beside the "
                          f"stem of a {p['span_mm']} mm span")
    outline = Polygon([(-a, -w), (a, -w), (a, w), (w, w), (w, w + st), (-w, w + st), (-w, w),
                       (-a, w)])
    return trimesh.creation.extrude_polygon(outline, p["height_mm"])


def _triangle(p: dict[str, float]) -> trimesh.Trimesh:
    b, d = p["base_mm"] / 2, p["depth_mm"]
    outline = Polygon([(-b, 0.0), (b, 0.0), (0.0, d)])  # re-centred on the plate after
    return trimesh.creation.extrude_polygon(outline, p["height_mm"])
