"""Mesh outputs: per-layer deviation PLY with scalar fields, reference STL."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2.defects.deviation import LayerDeviation
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
    t = np.clip(signed_distance_mm / max(limit_mm, 1e-9), -1.0, 1.0) * 0.5 + 0.5
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

    n = dev.n_vertices
    vdt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                    ("blue", "u1"), ("scalar_signed_distance", "<f4"), ("scalar_class", "<f4"),
                    ("scalar_weight", "<f4"), ("ref_x", "<f4"), ("ref_y", "<f4"),
                    ("ref_z", "<f4")])
    verts = np.empty(n, vdt)
    for k, name in enumerate("xyz"):
        verts[name] = dev.vertices_O[:, k]
    rgb = deviation_colours(dev.signed_distance_mm, dev.class_code, limit_mm)
    verts["red"], verts["green"], verts["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    verts["scalar_signed_distance"] = dev.signed_distance_mm
    verts["scalar_class"] = dev.class_code
    verts["scalar_weight"] = np.minimum(dev.weight, np.finfo(np.float32).max)
    for k, name in enumerate(("ref_x", "ref_y", "ref_z")):
        verts[name] = dev.foot_O[:, k]
    classes = ", ".join(f"{k} = {name}" for k, name in enumerate(CLASS_NAMES))
    fdt = np.dtype([("n", "u1"), ("v", "<i4", (3,))])
    faces = np.empty(len(dev.faces), fdt)
    faces["n"] = 3
    faces["v"] = dev.faces
    header = ("ply\nformat binary_little_endian 1.0\ncomment dm2 deviation map, frame O, mm\n"
              f"comment layer {dev.layer}\ncomment scalar_class: {classes}\n"
              "comment scalar_signed_distance: mm to the near-net reference, + above it\n"
              "comment ref_x ref_y ref_z: closest point on the near-net reference, mm\n"
              f"element vertex {n}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\n"
              "property float scalar_signed_distance\nproperty float scalar_class\n"
              "property float scalar_weight\n"
              "property float ref_x\nproperty float ref_y\nproperty float ref_z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(verts.tobytes())
        fh.write(faces.tobytes())


def read_ply_vertex_fields(path: str | Path) -> dict[str, np.ndarray]:
    """Vertex properties of a PLY written by :func:`write_deviation_ply` (for checks)."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    n = next(int(x.split()[2]) for x in lines if x.startswith("element vertex"))
    types = {"float": "<f4", "uchar": "u1", "int": "<i4"}
    props = []
    in_vertex = False
    for x in lines:
        if x.startswith("element"):
            in_vertex = x.startswith("element vertex")
        elif x.startswith("property") and in_vertex:
            _, t, name = x.split()
            props.append((name, types[t]))
    arr = np.frombuffer(data, np.dtype(props), count=n, offset=end)
    return {name: arr[name].copy() for name, _ in props}


def write_reference_stl(path: str | Path, reference: ReferenceMap, margin_mm: float = 3.0,
                        max_cells: int = 250_000) -> None:
    """The reference top surface as binary STL in ``O`` [mm], cropped to where material was
    deposited (plus ``margin_mm``) and thinned to at most about ``max_cells`` grid cells."""
    import trimesh

    h = reference.heights_mm
    c = reference.cell_mm
    rows, cols = np.nonzero(h > 1e-3)
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
