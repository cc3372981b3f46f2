"""Raster infill: parallel lines at the line spacing, clipped to a layer's region.

Lines run along the direction ``angle_rad`` (from +x_O, counter-clockwise). They are centred on
the region's extent across the raster so that buffering them by half a spacing covers it.
"""

from __future__ import annotations

import numpy as np
import shapely

from dm2.core.tolerances import DIVISOR_FLOOR

CLIP_INSET_MM = 0.05  # line ends stay this far inside the region, so short links between
# neighbouring ends stay inside it too (also along gently curved or slightly tilted edges)
COVER_SLACK = 0.05  # fraction of a spacing the raster may leave uncovered at each side
MIN_PIECE_MM = 0.05  # raster pieces shorter than this (grazing a corner) are dropped
MIN_SLIVER_LENGTH = 2.0  # uncovered strips longer than this many spacings get an extra line
PARALLEL_SIN = np.sin(np.radians(12.0))  # outline edges this close to the raster can leave strips


def raster_segments(region, angle_rad: float, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Clip a family of parallel raster lines to ``region``.

    Parameters
    ----------
    region : shapely (Multi)Polygon in O [mm]
    angle_rad : float [rad], raster direction
    spacing_mm : float [mm], distance between neighbouring lines

    Returns
    -------
    segments : (m, 2, 2) float64 [mm], start and end point of each clipped piece, each
        running along +direction
    scanline : (m,) int64, index of the raster line each piece lies on (0 = lowest offset)
    """
    empty = np.zeros((0, 2, 2)), np.zeros(0, dtype=np.int64)
    if region.is_empty:
        return empty
    clip = region.buffer(-CLIP_INSET_MM, join_style="mitre")
    if clip.is_empty:
        return empty
    direction = np.array([np.cos(angle_rad), np.sin(angle_rad)])
    across = np.array([-direction[1], direction[0]])
    coords = shapely.get_coordinates(clip)
    along_c, across_c = coords @ direction, coords @ across
    lo, hi = across_c.min(), across_c.max()
    n_lines = max(1, int(np.ceil((hi - lo) / spacing_mm - COVER_SLACK)))
    offsets = (lo + hi) / 2 + (np.arange(n_lines) - (n_lines - 1) / 2) * spacing_mm
    a0, a1 = along_c.min() - 1.0, along_c.max() + 1.0
    starts = offsets[:, None] * across + a0 * direction
    ends = offsets[:, None] * across + a1 * direction
    lines = shapely.linestrings(np.stack([starts, ends], axis=1))
    clipped = shapely.intersection(lines, clip)
    clipped, index_extra = _fill_slivers(clipped, clip, direction, across, offsets, spacing_mm,
                                         (a0, a1))
    parts, index = shapely.get_parts(clipped, return_index=True)
    index = index_extra[index]
    keep = shapely.get_type_id(parts) == 1  # LineString pieces only (drop touching points)
    parts, index = parts[keep], index[keep]
    if len(parts) == 0:
        return empty
    segs = np.empty((len(parts), 2, 2))
    for i, p in enumerate(parts):
        c = shapely.get_coordinates(p)
        segs[i, 0], segs[i, 1] = c[0], c[-1]
    long_enough = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1) >= MIN_PIECE_MM
    segs, index = segs[long_enough], index[long_enough]
    flip = (segs[:, 1] - segs[:, 0]) @ direction < 0
    segs[flip] = segs[flip][:, ::-1]
    order = np.lexsort(((segs[:, 0] @ direction), index))
    return segs[order], index[order].astype(np.int64)


def _fill_slivers(clipped, clip, direction, across, offsets, spacing_mm, along_range):
    """Add raster lines through long uncovered strips (edges parallel to the raster).

    Where an outline edge runs parallel to the raster between two lines, buffering the lines
    by half a spacing leaves a strip uncovered; a line along the middle of each such strip
    (clipped to the region near it) closes it. Returns the clipped geometries and, for each,
    the index of the nearest regular raster line.
    """
    index = np.arange(len(clipped))
    if not _has_parallel_run(clip, direction, MIN_SLIVER_LENGTH * spacing_mm):
        return clipped, index
    covered = shapely.union_all(shapely.buffer(clipped, spacing_mm / 2, quad_segs=4))
    missing = clip.difference(covered)
    extra, extra_index = [], []
    for piece in shapely.get_parts(missing):
        if piece.area < 0.25 * spacing_mm ** 2:
            continue
        c = shapely.get_coordinates(piece)
        if np.ptp(c @ direction) < MIN_SLIVER_LENGTH * spacing_mm:
            continue
        off = (np.max(c @ across) + np.min(c @ across)) / 2
        line = shapely.linestrings([off * across + along_range[0] * direction,
                                    off * across + along_range[1] * direction])
        extra.append(shapely.intersection(line, clip.intersection(piece.buffer(spacing_mm / 2))))
        extra_index.append(int(np.argmin(np.abs(offsets - off))))
    if not extra:
        return clipped, index
    return np.concatenate([clipped, np.asarray(extra, dtype=object)]), \
        np.concatenate([index, extra_index])


def _has_parallel_run(region, direction, min_length_mm: float) -> bool:
    """Whether some stretch of the outline, ``min_length_mm`` long, runs along the raster."""
    for ring in shapely.get_rings(shapely.get_parts(region)):
        c = shapely.get_coordinates(ring)
        e = np.diff(c, axis=0)
        length = np.linalg.norm(e, axis=1)
        cross = e[:, 0] * direction[1] - e[:, 1] * direction[0]
        sin = np.abs(cross) / np.maximum(length, DIVISOR_FLOOR)
        par = sin < PARALLEL_SIN
        if not par.any():
            continue
        if par.all():
            return True
        start = int(np.argmin(par))  # begin the scan on a non-parallel edge (runs wrap)
        run = 0.0
        for ok, ln in zip(np.roll(par, -start), np.roll(length, -start), strict=True):
            run = run + ln if ok else 0.0
            if run >= min_length_mm:
                return True
    return False
