"""Mesh outputs: per-layer deviation PLY with scalar fields, reference STL."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2.core.tolerances import BUILT_HEIGHT_MM, RATIO_FLOOR
from dm2.defects.deviation import LayerDeviation
from dm2.io.ply import read_mesh_ply, write_mesh_ply
from dm2.reference.height_map import ReferenceMap

CLASS_RGB = np.array([[200, 200, 200],   # normal
                      [215, 48, 39],     # overbuild
                      [69, 117, 180],    # underbuild
                      [253, 174, 97],    # local overbuild
                      [153, 112, 171],   # local underbuild
                      [90, 90, 90]], np.uint8)  # unobserved


def deviation_colours(signed_distance_mm: np.ndarray, class_code: np.ndarray,
                      limit_mm: float) -> np.ndarray:
    """(n, 3) uint8: diverging blue-white-red by signed distance clipped to ``+-limit_mm``;
    unobserved vertices grey."""
    import matplotlib

    cmap = matplotlib.colormaps["RdBu_r"]
    t = np.clip(signed_distance_mm / max(limit_mm, RATIO_FLOOR), -1.0, 1.0) * 0.5 + 0.5
    rgb = (cmap(t)[:, :3] * 255).astype(np.uint8)
    rgb[class_code == len(CLASS_RGB) - 1] = CLASS_RGB[-1]
    return rgb


def write_deviation_ply(path: str | Path, dev: LayerDeviation, limit_mm: float = 1.0) -> None:
    """Binary little-endian PLY of the layer's mesh with colours and scalar fields.

    Vertex properties: ``x y z`` (float32, mm, frame O), ``red green blue`` (uchar),
    ``scalar_signed_distance`` (float32, mm), ``scalar_class`` (float32 class code),
    ``scalar_weight`` (float32), ``ref_x ref_y ref_z`` (float32, mm, frame O: the closest
    point of the near-net reference to the vertex, so the same faces over these points show the
    reference surface); CloudCompare shows the ``scalar_*`` ones as scalar fields. The header
    comments name each ``scalar_class`` code (:data:`dm2.defects.classify.CLASS_NAMES`).
    """
    from dm2.defects.classify import CLASS_NAMES

    v = dev.vertices_O.astype(np.float32)
    foot = np.asarray(dev.foot_O, dtype=np.float32)
    rgb = deviation_colours(dev.signed_distance_mm, dev.class_code, limit_mm)
    fields = {"x": v[:, 0], "y": v[:, 1], "z": v[:, 2],
              "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2],
              "scalar_signed_distance": np.asarray(dev.signed_distance_mm, dtype=np.float32),
              "scalar_class": np.asarray(dev.class_code, dtype=np.float32),
              "scalar_weight": np.minimum(dev.weight, np.finfo(np.float32).max).astype(np.float32),
              "ref_x": foot[:, 0], "ref_y": foot[:, 1], "ref_z": foot[:, 2]}
    classes = ", ".join(f"{k} = {name}" for k, name in enumerate(CLASS_NAMES))
    write_mesh_ply(path, fields, dev.faces,
                   comments=["dm2 deviation map, frame O, mm", f"layer {dev.layer}",
                             f"scalar_class: {classes}",
                             "scalar_signed_distance: mm to the near-net reference, + above it",
                             "ref_x ref_y ref_z: closest point on the near-net reference, mm"])


def read_ply_vertex_fields(path: str | Path) -> dict[str, np.ndarray]:
    """Vertex properties of a deviation map PLY (:func:`write_deviation_ply`), by name."""
    return read_mesh_ply(path)[0]


def write_reference_stl(path: str | Path, reference: ReferenceMap, margin_mm: float = 3.0,
                        max_cells: int = 250_000) -> None:
    """The reference top surface as binary STL in ``O`` [mm], cropped to where material was
    deposited (plus ``margin_mm``) and thinned to at most about ``max_cells`` grid cells."""
    import trimesh

    h = reference.heights_mm
    c = reference.cell_mm
    rows, cols = np.nonzero(h > BUILT_HEIGHT_MM)
    if rows.size:
        lo = np.array([cols.min(), rows.min()]) * c
        hi = np.array([cols.max() + 1, rows.max() + 1]) * c
        rs, cs = reference.crop_indices(lo, hi, margin_mm)
    else:
        rs, cs = slice(0, h.shape[0]), slice(0, h.shape[1])
    sub = h[rs, cs]
    step = max(int(np.ceil(np.sqrt(sub.size / max_cells))), 1)
    sub = sub[::step, ::step]
    ny, nx = sub.shape
    x = (cs.start + np.arange(nx) * step + 0.5) * c
    y = (rs.start + np.arange(ny) * step + 0.5) * c
    xx, yy = np.meshgrid(x, y)
    verts = np.column_stack([xx.ravel(), yy.ravel(), sub.ravel()])
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    d, e = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, e]), np.column_stack([a, e, d])])
    trimesh.Trimesh(verts, faces, process=False).export(str(path), file_type="stl")
