"""The paper's Tables 1-2 and area/height-per-layer figures, from a run folder's files.

Heights come from a top-surface height map on a regular xy grid (the largest z of the surface
vertices per cell): the twin's true surface of the last layer (``truth/layer_NNN.ply``) or the
reconstructed surface of the last layer (``meshes/layer_NNN.ply``). The part's footprint is
where the height exceeds half its 95th percentile; the *edge* is the footprint band within
``edge_band_mm`` of its outline, the *centre* the cells at least half the footprint's largest
inner distance from the outline. Heights are medians over those cells; the average layer
height is the edge (centre) height over the number of layers; the deposited mass is the
volume above the plate times the powder density.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dm2.core.tolerances import BUILT_HEIGHT_MM

EDGE_BAND_MM = 3.0
GRID_MM = 0.5


def height_map(vertices_O: np.ndarray, cell_mm: float = GRID_MM):
    """(heights (ny, nx) [mm] with NaN where no vertex fell, x0, y0) from surface vertices."""
    v = np.asarray(vertices_O, dtype=np.float64)
    x0, y0 = v[:, 0].min(), v[:, 1].min()
    i = np.floor((v[:, 0] - x0) / cell_mm).astype(np.int64)
    j = np.floor((v[:, 1] - y0) / cell_mm).astype(np.int64)
    h = np.full((j.max() + 1, i.max() + 1), -np.inf)
    np.maximum.at(h, (j, i), v[:, 2])
    h[~np.isfinite(h)] = np.nan
    return h, x0, y0


def part_heights(vertices_O: np.ndarray, n_layers: int, density_g_cm3: float,
                 cell_mm: float = GRID_MM, edge_band_mm: float = EDGE_BAND_MM) -> dict:
    """Edge and centre height, average layer heights and deposited mass of a top surface."""
    from scipy import ndimage

    h, _, _ = height_map(vertices_O, cell_mm)
    filled = h.copy()
    holes = np.isnan(filled)
    if holes.any() and (~holes).any():  # unobserved cells take their nearest neighbour
        idx = ndimage.distance_transform_edt(holes, return_distances=False, return_indices=True)
        filled = filled[tuple(idx)]
    built = filled > BUILT_HEIGHT_MM
    top = np.percentile(filled[built], 95) if np.any(built) else 0.0
    footprint = filled > 0.5 * top if top > 0 else np.zeros(filled.shape, bool)
    if not footprint.any():
        return {"edge_height_mm": 0.0, "centre_height_mm": 0.0, "avg_edge_layer_mm": 0.0,
                "avg_centre_layer_mm": 0.0, "mass_g": 0.0, "coverage": 0.0}
    inner = ndimage.distance_transform_edt(footprint) * cell_mm
    edge = footprint & (inner <= edge_band_mm)
    centre = footprint & (inner >= 0.5 * inner.max())
    edge_h = float(np.median(filled[edge]))
    centre_h = float(np.median(filled[centre]))
    volume_mm3 = float(np.clip(filled, 0.0, None).sum() * cell_mm * cell_mm)
    n = max(int(n_layers), 1)
    return {"edge_height_mm": edge_h, "centre_height_mm": centre_h,
            "avg_edge_layer_mm": edge_h / n, "avg_centre_layer_mm": centre_h / n,
            "mass_g": volume_mm3 * density_g_cm3 / 1000.0,
            "coverage": float(1.0 - holes[footprint].mean())}


def paper_table_row(run_dir: str | Path, report: dict, density_g_cm3: float) -> dict:
    """Truth and reconstruction columns of the paper's tables for one run folder."""
    import trimesh

    run_dir = Path(run_dir)
    layers = [ly["layer"] for ly in report.get("layers", [])]
    row = {"scenario": report.get("meta", {}).get("scenario"), "layers": len(layers)}
    if not layers:
        return row
    last = max(layers)
    n = last + 1
    for label, path in (("truth", run_dir / "truth" / f"layer_{last:03d}.ply"),
                        ("reconstruction", run_dir / "meshes" / f"layer_{last:03d}.ply")):
        if path.exists():
            v = np.asarray(trimesh.load(path, force="mesh").vertices)
            row[label] = part_heights(v, n, density_g_cm3)
    return row


def track_evolution_figure(report: dict, title: str):
    """Area (top axes) and peak deviation (bottom axes) of every global track, and of local
    tracks seen in two layers or more, against layer (the paper's Figs. 'evolution')."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_a, ax_h) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for t in report.get("tracks", []):
        if t["kind"].startswith("local_") and len(t["history"]) < 2:
            continue
        layers = [h["layer"] for h in t["history"]]
        style = "-" if not t["kind"].startswith("local_") else ":"
        label = f"#{t['id']} {t['kind']}"
        ax_a.plot(layers, [h["area_mm2"] for h in t["history"]], style, marker="o", ms=3,
                  label=label)
        ax_h.plot(layers, [h["max_deviation_mm"] for h in t["history"]], style, marker="o",
                  ms=3, label=label)
    ax_a.set_ylabel("defect area [mm²]")
    ax_h.set_ylabel("peak deviation [mm]")
    ax_h.set_xlabel("layer")
    ax_a.set_title(title)
    if ax_a.get_legend_handles_labels()[0]:
        ax_a.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return fig


def plot_track_evolution(path: str | Path, report: dict, title: str) -> Path:
    """:func:`track_evolution_figure` saved as a PNG at ``path``."""
    import matplotlib.pyplot as plt

    fig = track_evolution_figure(report, title)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def format_table_markdown(rows: list[dict]) -> str:
    """The Tables 1-2 analogue as Markdown (truth / reconstruction per column)."""
    head = ("| scenario | layers | edge height mm | avg edge layer mm | centre height mm | "
            "avg centre layer mm | mass g |\n|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        t, m = r.get("truth", {}), r.get("reconstruction", {})

        def pair(key, fmt="{:.2f}", t=t, m=m):
            a = fmt.format(t[key]) if key in t else "-"
            b = fmt.format(m[key]) if key in m else "-"
            return f"{a} / {b}"
        lines.append(f"| {r['scenario']} | {r['layers']} | {pair('edge_height_mm')} | "
                     f"{pair('avg_edge_layer_mm', '{:.3f}')} | {pair('centre_height_mm')} | "
                     f"{pair('avg_centre_layer_mm', '{:.3f}')} | {pair('mass_g')} |")
    return "\n".join(lines) + "\n\n(truth / reconstruction)\n"
