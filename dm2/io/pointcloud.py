"""``sensor_msgs/msg/PointCloud2`` as profiler drivers publish it, turned into laser-line points.

Accepted: ``x, y, z`` as FLOAT32 or FLOAT64 (little or big endian), an optional ``intensity``
of any numeric type (FLOAT as is; integer types scaled by their maximum to 0..1), organised
(``height > 1``, rows of ``row_step`` bytes, padding allowed) or not. Points are taken in row
order. An invalid return is a point with a NaN or infinite coordinate, or exactly
``(0, 0, 0)`` (what drivers publishing ``is_dense = true`` clouds write instead).

A profile lies in its sensor's x-z plane: :func:`profile_points` drops points further than
``plane_tol_mm`` from it and counts them (a whole topic off-plane usually means the cloud's
frame is not the sensor frame the map names).
"""

from __future__ import annotations

import numpy as np

from dm2.io.ros_messages import MM_PER_M

_FLOAT = {7: "f4", 8: "f8"}
_NUMERIC = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
PLANE_TOL_MM = 0.5  # largest |y_S| [mm] of a point that still lies in the laser plane


class CloudError(ValueError):
    """A PointCloud2 whose layout cannot be read."""


def cloud_xyz(msg) -> tuple[np.ndarray, np.ndarray]:
    """``(xyz_m (n, 3) float64 with NaN rows where invalid, intensity (n,) float32)`` of a
    deserialised PointCloud2 ``msg`` (any object with its fields)."""
    fields = {f.name: f for f in msg.fields}
    end = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for name in ("x", "y", "z"):
        f = fields.get(name)
        if f is None:
            raise CloudError(f"PointCloud2 has no field {name!r} (fields: {sorted(fields)})")
        if f.datatype not in _FLOAT:
            raise CloudError(f"PointCloud2 field {name!r} has datatype {f.datatype}; x, y, z "
                             "must be FLOAT32 (7) or FLOAT64 (8)")
        names.append(name)
        formats.append(end + _FLOAT[f.datatype])
        offsets.append(f.offset)
    fi = fields.get("intensity")
    if fi is not None:
        if fi.datatype not in _NUMERIC:
            raise CloudError(f"PointCloud2 field 'intensity' has datatype {fi.datatype}")
        names.append("intensity")
        formats.append(end + _NUMERIC[fi.datatype])
        offsets.append(fi.offset)
    step, height, width = int(msg.point_step), int(msg.height), int(msg.width)
    sizes = [np.dtype(fmt).itemsize for fmt in formats]
    if any(o + s > step for o, s in zip(offsets, sizes, strict=True)):
        raise CloudError(f"PointCloud2 fields reach past point_step = {step}")
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                      "itemsize": step})
    raw = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    row_step = int(msg.row_step) if height > 1 else width * step
    if row_step < width * step or raw.size < (height - 1) * row_step + width * step:
        raise CloudError(f"PointCloud2 data ({raw.size} bytes) shorter than height = {height} "
                         f"rows of width = {width} points of {step} bytes (row_step "
                         f"{row_step})")
    if height == 0 or width == 0:
        return np.empty((0, 3)), np.empty(0, np.float32)
    if row_step == width * step:
        pts = raw[:height * row_step].view(dtype)
    else:
        rows = [raw[r * row_step: r * row_step + width * step].view(dtype) for r in range(height)]
        pts = np.concatenate(rows)
    xyz = np.column_stack([pts["x"].astype(np.float64), pts["y"].astype(np.float64),
                           pts["z"].astype(np.float64)])
    bad = ~np.isfinite(xyz).all(axis=1) | (xyz == 0.0).all(axis=1)
    xyz[bad] = np.nan
    if fi is None:
        inten = np.zeros(xyz.shape[0], np.float32)
    else:
        v = pts["intensity"]
        if np.issubdtype(v.dtype, np.integer):
            inten = (v.astype(np.float64) / np.iinfo(v.dtype).max).astype(np.float32)
        else:
            inten = np.nan_to_num(v.astype(np.float32))
    return xyz, inten


def profile_points(xyz_m: np.ndarray, T_S_C: np.ndarray | None = None,
                   plane_tol_mm: float = PLANE_TOL_MM) -> tuple[np.ndarray, np.ndarray, int]:
    """``(xz_S [mm] (n, 2) NaN where invalid, valid (n,), n_off_plane)`` of cloud points
    ``xyz_m`` in frame ``C``; ``T_S_C`` (mm) maps them into the sensor frame (None: C is S)."""
    p_mm = xyz_m * MM_PER_M
    if T_S_C is not None:
        p_mm = p_mm @ T_S_C[:3, :3].T + T_S_C[:3, 3]
    finite = np.isfinite(p_mm).all(axis=1)
    off = finite & (np.abs(np.nan_to_num(p_mm[:, 1])) > plane_tol_mm)
    valid = finite & ~off
    xz = p_mm[:, [0, 2]].copy()
    xz[~valid] = np.nan
    return xz, valid, int(off.sum())
