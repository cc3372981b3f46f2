"""Top-view plot of toolpath layers, coloured by kind like the paper's toolpath figure."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2.core.messages import TOOLPATH_KINDS, Toolpath

KIND_COLOURS = {"infill": "tab:blue", "edge": "red", "skip": "green", "overhang": "cyan"}


def default_layers(tp: Toolpath) -> list[int]:
    """The first and the last layer (as the paper shows layers 1 and 62)."""
    return sorted({0, max(tp.n_layers - 1, 0)})


def plot_toolpath(tp: Toolpath, path: str | Path, layers: list[int] | None = None) -> None:
    """Write a PNG with one top-view panel per layer; each move is drawn in its kind's colour.

    Parameters
    ----------
    tp : Toolpath
    path : output PNG path
    layers : layer indices to show (default: first and last)
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    layers = default_layers(tp) if layers is None else list(layers)
    bad = [k for k in layers if not 0 <= k < tp.n_layers]
    if bad:
        raise ValueError(f"plot layers {bad} outside 0..{tp.n_layers - 1}")
    fig, axes = plt.subplots(1, len(layers), figsize=(6 * len(layers), 6), squeeze=False)
    colours = np.array([KIND_COLOURS[k] for k in TOOLPATH_KINDS], dtype=object)
    for ax, k in zip(axes[0], layers, strict=True):
        idx = np.flatnonzero(tp.layer == k)
        idx = idx[idx > 0]
        segs = np.stack([tp.position_O[idx - 1, :2], tp.position_O[idx, :2]], axis=1)
        ax.add_collection(LineCollection(segs, colors=list(colours[tp.kind[idx]]), linewidths=1))
        ax.autoscale()
        ax.set_aspect("equal")
        ax.set_title(f"layer {k + 1} (index {k})")
        ax.set_xlabel("x_O [mm]")
        ax.set_ylabel("y_O [mm]")
    handles = [Line2D([], [], color=c, label=k) for k, c in KIND_COLOURS.items()]
    fig.legend(handles=handles, loc="upper center", ncol=4)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    fig.savefig(path, dpi=110, metadata={"Software": "dm2"})  # marks the file as dm2's
    plt.close(fig)
