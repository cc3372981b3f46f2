"""Headless PNG plots: top-view deviation maps and per-track area/height against layer."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2.defects.deviation import LayerDeviation
from dm2.defects.segment import Region
from dm2.defects.track import Track


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def plot_deviation_map(path: str | Path, dev: LayerDeviation, regions: list[Region] = (),
                       track_ids: list[int] = (), limit_mm: float = 1.0,
                       title: str | None = None) -> None:
    """Top view (xy in ``O``) of the layer's mesh coloured by signed distance, with the
    regions' bounding boxes and track ids; unobserved vertices are hatched grey."""
    plt = _pyplot()
    from matplotlib.patches import Rectangle
    from matplotlib.tri import Triangulation

    fig, ax = plt.subplots(figsize=(7, 6), dpi=110)
    try:
        v = dev.vertices_O
        if len(dev.faces):
            tri = Triangulation(v[:, 0], v[:, 1], dev.faces)
            seen = dev.class_code != 5
            d = np.where(seen, dev.signed_distance_mm, np.nan)
            face_d = np.nanmean(np.where(np.isfinite(d[dev.faces]), d[dev.faces], np.nan), axis=1) \
                if np.isfinite(d).any() else np.full(len(dev.faces), np.nan)
            mask = ~np.isfinite(face_d)
            tri.set_mask(mask)
            pc = ax.tripcolor(tri, facecolors=np.nan_to_num(face_d), cmap="RdBu_r",
                              vmin=-limit_mm, vmax=limit_mm)
            fig.colorbar(pc, ax=ax, label="signed distance to reference [mm]")
            if mask.any():
                grey = Triangulation(v[:, 0], v[:, 1], dev.faces[mask])
                ax.triplot(grey, color="0.6", lw=0.2)
        for r, tid in zip(regions, list(track_ids) + [None] * len(regions), strict=False):
            lo, hi = r.bbox_min_O, r.bbox_max_O
            colour = "darkred" if "over" in r.kind else "navy"
            ax.add_patch(Rectangle(lo[:2], *(hi[:2] - lo[:2]), fill=False, ec=colour, lw=1.2))
            label = f"#{tid} " if tid is not None else ""
            ax.annotate(f"{label}{r.kind}\n{r.area_mm2:.0f} mm$^2$, h {r.height_mm:.2f} mm",
                        (hi[0], hi[1]), fontsize=7, color=colour)
        ax.set_aspect("equal")
        ax.set_xlabel("x_O [mm]")
        ax.set_ylabel("y_O [mm]")
        ax.set_title(title or f"Layer {dev.layer}: deviation map")
        fig.tight_layout()
        fig.savefig(path)
    finally:
        plt.close(fig)


def plot_track(path: str | Path, track: Track) -> None:
    """Area [mm^2] and height [mm] of one track against layer (as the paper's figures)."""
    plt = _pyplot()
    from matplotlib.ticker import MaxNLocator

    layers, area = track.series("area_mm2")
    _, height = track.series("height_mm")
    fig, ax1 = plt.subplots(figsize=(6, 3.6), dpi=110)
    try:
        ax1.plot(layers, area, "o-", color="tab:red", label="surface area")
        ax1.set_xlabel("layer")
        ax1.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax1.set_ylabel("area [mm$^2$]", color="tab:red")
        ax2 = ax1.twinx()
        ax2.plot(layers, height, "s--", color="tab:blue", label="height")
        ax2.set_ylabel("height [mm]", color="tab:blue")
        ax1.set_title(f"Track {track.id}: {track.kind} ({track.trend})")
        fig.tight_layout()
        fig.savefig(path)
    finally:
        plt.close(fig)
