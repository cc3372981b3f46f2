"""Headless PNG plots: deviation maps with the planned outline and numbered track markers, the
track x layer timeline, and per-track area / height against layer.

Maps carry no floating text: each track is a numbered marker (its id, keyed to the report's
table) at its centroid. A track's height is its largest deviation from the reference.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2.defects.deviation import LayerDeviation

KIND_COLOURS = {"overbuild": "#b2182b", "underbuild": "#2166ac",
                "local_overbuild": "#f4a582", "local_underbuild": "#92c5de"}
MAP_MARGIN_MM = 8.0  # around the outline and the markers
TIMELINE_ROWS = 40  # tracks shown on the timeline (most severe)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def deviation_raster(dev: LayerDeviation, pixel_mm: float | None = None):
    """Top view of a layer's signed distance on a regular xy grid: ``(image (ny, nx) with NaN
    where nothing was measured, unobserved (ny, nx) bool, extent (x0, x1, y0, y1) mm)``.

    Each pixel holds the mean signed distance of the observed vertices in it (pixels about the
    mesh's vertex spacing; one pass fills isolated empty pixels from their neighbours).
    """
    v = dev.vertices_O
    if pixel_mm is None:
        a = dev.vertex_area_mm2
        pixel_mm = float(np.sqrt(np.median(a[a > 0]))) if np.any(a > 0) else 0.5
        pixel_mm = min(max(pixel_mm, 0.1), 2.0)
    lo = v[:, :2].min(axis=0) - pixel_mm
    nx, ny = (np.ceil((v[:, :2].max(axis=0) + pixel_mm - lo) / pixel_mm).astype(int) + 1)
    ij = np.floor((v[:, :2] - lo) / pixel_mm).astype(np.int64)
    flat = ij[:, 1] * nx + ij[:, 0]
    seen = dev.class_code != 5
    total = np.bincount(flat[seen], dev.signed_distance_mm[seen], nx * ny)
    count = np.bincount(flat[seen], minlength=nx * ny).astype(float)
    blind = np.bincount(flat[~seen], minlength=nx * ny) > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        img = (total / count).reshape(ny, nx)
    empty = count.reshape(ny, nx) == 0
    if empty.any():  # isolated holes between vertices: the mean of the 3 x 3 neighbours
        t2, c2 = total.reshape(ny, nx), count.reshape(ny, nx)
        ts, cs = np.zeros_like(t2), np.zeros_like(c2)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                ts += np.roll(np.roll(t2, dy, 0), dx, 1)
                cs += np.roll(np.roll(c2, dy, 0), dx, 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            fill = ts / cs
        fill_here = empty & (cs >= 3)
        img[fill_here] = fill[fill_here]
    unobserved = blind.reshape(ny, nx) & ~np.isfinite(img)
    extent = (lo[0], lo[0] + nx * pixel_mm, lo[1], lo[1] + ny * pixel_mm)
    return img, unobserved, extent


def _draw_deviation(fig, ax, dev: LayerDeviation, limit_mm: float) -> None:
    if dev.n_vertices == 0:
        return
    img, unobserved, extent = deviation_raster(dev)
    if unobserved.any():
        grey = np.where(unobserved, 0.75, np.nan)
        ax.imshow(grey, origin="lower", extent=extent, cmap="gray", vmin=0, vmax=1,
                  interpolation="nearest")
    im = ax.imshow(img, origin="lower", extent=extent, cmap="RdBu_r", vmin=-limit_mm,
                   vmax=limit_mm, interpolation="nearest")
    fig.colorbar(im, ax=ax, label="signed distance to reference [mm]", shrink=0.85)


def _draw_markers(ax, markers) -> list[np.ndarray]:
    """``markers``: (id, kind, (x, y)); a numbered circle each. Returns their points."""
    markers = list(markers)
    if not markers:
        return []
    xy = np.array([m[2] for m in markers], float)
    sizes = [110 + 45 * max(len(str(m[0])) - 1, 0) for m in markers]
    ax.scatter(xy[:, 0], xy[:, 1], s=sizes, facecolor="white", linewidth=1.8, zorder=5,
               edgecolor=[KIND_COLOURS.get(m[1], "k") for m in markers])
    for (tid, _, _), (x, y) in zip(markers, xy, strict=True):
        ax.text(x, y, str(tid), ha="center", va="center", fontsize=6.5, zorder=6,
                fontweight="bold")
    pts = list(xy)
    return pts


def _frame(ax, outline, pts) -> None:
    """Axis limits around the outline and the markers (the overspray beyond is cut off)."""
    for poly in outline or []:
        ax.plot(poly[:, 0], poly[:, 1], color="k", lw=1.2, ls="--", zorder=4)
    keep = [np.asarray(p)[:, :2] for p in (outline or [])] + [np.atleast_2d(p) for p in pts]
    if keep:
        allp = np.vstack(keep)
        lo, hi = allp.min(axis=0) - MAP_MARGIN_MM, allp.max(axis=0) + MAP_MARGIN_MM
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x_O [mm]")
    ax.set_ylabel("y_O [mm]")


def plot_deviation_map(path: str | Path, dev: LayerDeviation, markers=(), limit_mm: float = 1.0,
                       title: str | None = None, outline=None, dpi: int = 110) -> None:
    """Top view (xy in ``O``) of a layer's mesh coloured by signed distance (symmetric
    ``+-limit_mm``, unobserved faces grey wire), the planned ``outline`` dashed and each of
    ``markers`` = ``[(track_id, kind, (x, y)), ...]`` as a numbered circle."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 6), dpi=dpi)
    try:
        _draw_deviation(fig, ax, dev, limit_mm)
        pts = _draw_markers(ax, markers)
        _frame(ax, outline, pts)
        ax.set_title(title or f"Layer {dev.layer}: deviation map", fontsize=10)
        fig.subplots_adjust(left=0.1, right=0.97, top=0.94, bottom=0.08)
        fig.savefig(path)
    finally:
        plt.close(fig)


def plot_timeline(path: str | Path, tracks: list[dict], alarm_marks=(), n_layers: int = 0,
                  dpi: int = 100) -> int:
    """Gantt-style chart: one row per track (``tracks`` in the order to draw, top first), a
    bar per layer it was seen, coloured by kind; ``alarm_marks`` = ``[(layer, track_id or
    None), ...]`` as black triangles on their track's row (a row of their own when no track
    matched). Returns the number of rows drawn."""
    plt = _pyplot()
    from matplotlib.patches import Patch
    from matplotlib.ticker import MaxNLocator

    rows = list(tracks)
    orphan = [lay for lay, tid in alarm_marks if tid is None and lay is not None]
    n_rows = len(rows) + (1 if orphan else 0)
    fig, ax = plt.subplots(figsize=(9, 1.2 + 0.24 * max(n_rows, 1)), dpi=dpi)
    try:
        y_of = {}
        for i, t in enumerate(rows):
            y_of[t["id"]] = i
            spans = [(h["layer"] - 0.45, 0.9) for h in t["history"]]
            ax.broken_barh(spans, (i - 0.38, 0.76), color=KIND_COLOURS.get(t["kind"], "0.5"))
        labels = [f"#{t['id']} {t['kind'].replace('_', ' ')}" for t in rows]
        if orphan:
            labels.append("alarm, no track")
        for lay, tid in alarm_marks:
            if lay is None:
                continue
            y = y_of.get(tid, len(rows)) if tid is not None else len(rows)
            if tid is not None and tid not in y_of:
                continue
            ax.scatter([lay], [y], marker="v", color="k", s=28, zorder=5)
        ax.set_yticks(range(n_rows), labels, fontsize=7)
        ax.set_ylim(max(n_rows, 1) - 0.5, -0.5)
        last = max([n_layers - 1] + [t["last_layer"] for t in rows])
        ax.set_xlim(-0.6, last + 0.6)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlabel("layer")
        ax.grid(axis="x", color="0.9")
        handles = [Patch(color=c, label=k.replace("_", " ")) for k, c in KIND_COLOURS.items()]
        handles.append(plt.Line2D([], [], marker="v", color="k", ls="", label="real-time alarm"))
        ax.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
        fig.tight_layout()
        fig.savefig(path)
    finally:
        plt.close(fig)
    return n_rows


