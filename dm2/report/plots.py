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


def _draw_deviation(fig, ax, dev: LayerDeviation, limit_mm: float) -> None:
    from matplotlib.tri import Triangulation

    v = dev.vertices_O
    if not len(dev.faces):
        return
    tri = Triangulation(v[:, 0], v[:, 1], dev.faces)
    seen = dev.class_code != 5
    d = np.where(seen, dev.signed_distance_mm, np.nan)[dev.faces]
    with np.errstate(invalid="ignore"):
        face_d = np.nanmean(d, axis=1) if np.isfinite(d).any() else np.full(len(d), np.nan)
    mask = ~np.isfinite(face_d)
    tri.set_mask(mask)
    pc = ax.tripcolor(tri, facecolors=np.nan_to_num(face_d), cmap="RdBu_r", vmin=-limit_mm,
                      vmax=limit_mm, rasterized=True)
    fig.colorbar(pc, ax=ax, label="signed distance to reference [mm]", shrink=0.85)
    if mask.any():
        grey = Triangulation(v[:, 0], v[:, 1], dev.faces[mask])
        ax.triplot(grey, color="0.7", lw=0.15)


def _draw_markers(ax, markers) -> list[np.ndarray]:
    """``markers``: (id, kind, (x, y)); a numbered circle each. Returns their points."""
    pts = []
    for tid, kind, (x, y) in markers:
        label = str(tid)
        ax.scatter([x], [y], s=110 + 45 * max(len(label) - 1, 0), facecolor="white",
                   edgecolor=KIND_COLOURS.get(kind, "k"), linewidth=1.8, zorder=5)
        ax.text(x, y, label, ha="center", va="center", fontsize=6.5, zorder=6,
                fontweight="bold")
        pts.append(np.array([x, y]))
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
        ax.set_title(title or f"Layer {dev.layer}: deviation map")
        fig.tight_layout()
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
        ax.set_ylim(n_rows - 0.5, -0.5)
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


def plot_track(path: str | Path, track: dict) -> None:
    """Area [mm^2] (top) and height = signed max deviation [mm] (bottom) of one track (a report
    track dict) against layer, on integer layer ticks."""
    plt = _pyplot()
    from matplotlib.ticker import MaxNLocator

    layers = [h["layer"] for h in track["history"]]
    area = [h["area_mm2"] for h in track["history"]]
    dev = [h["max_deviation_mm"] for h in track["history"]]
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(6, 4.2), dpi=100, sharex=True)
    try:
        colour = KIND_COLOURS.get(track["kind"], "k")
        ax1.plot(layers, area, "o-", color=colour)
        ax1.set_ylabel("area [mm$^2$]")
        ax1.set_ylim(bottom=0)
        ax2.plot(layers, dev, "s-", color=colour)
        ax2.axhline(0, color="0.6", lw=0.8)
        ax2.set_ylabel("max deviation [mm]")
        ax2.set_xlabel("layer")
        ax2.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax2.set_xlim(min(layers) - 0.6, max(layers) + 0.6)
        ax1.set_title(f"Track {track['id']}: {track['kind'].replace('_', ' ')} "
                      f"({track.get('trend', '')})")
        fig.tight_layout()
        fig.savefig(path)
    finally:
        plt.close(fig)
