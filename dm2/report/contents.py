"""The files of a report folder besides report.json and index.html, with bounded cost.

Per layer: one deviation PLY. Maps: up to :data:`MAP_LAYERS` layers (spread evenly, plus the
first layer of the most severe defect tracks, always the last). Figures: the overview (last
layer's map, planned outline, the :data:`MARKED_TRACKS` most severe tracks as numbered
markers) and the track x layer timeline; one plot per track only for the
:data:`PLOTTED_TRACKS` most severe. Every other track is in the table and the timeline data.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from dm2.report import summary
from dm2.report.meshes import write_deviation_ply, write_reference_stl
from dm2.report.plots import KIND_COLOURS, TIMELINE_ROWS, plot_deviation_map, plot_timeline
from dm2.report.report_json import write_tracks_csv
from dm2.report.svg_plots import write_track_svgs

PLOTTED_TRACKS = 20
MARKED_TRACKS = 20
MAP_LAYERS = 12
MAP_MARKERS = 30  # numbered markers per layer map at most (largest regions)

Stage = Callable[[str, int, int], None]  # (stage name, steps done, steps in the stage)


def default_map_layers(layers: list[int], ranked: list[dict], n: int = MAP_LAYERS) -> list[int]:
    """Up to ``n`` layers: six spread evenly (first and last included), then the first layers
    of the most severe defect tracks."""
    keys = sorted(layers)
    if not keys:
        return []
    idx = sorted({round(i * (len(keys) - 1) / 5) for i in range(6)})
    chosen = {keys[i] for i in idx}
    for t in ranked:
        if len(chosen) >= n:
            break
        if summary.is_defect(t) and t["first_layer"] in keys:
            chosen.add(t["first_layer"])
    return sorted(chosen)


def write_contents(tmp: Path, results, tracks, ranked: list[dict], *, config_toml, map_layers,
                   limit_mm: float, outline, report_stub: dict,
                   stage: Stage | None = None) -> dict:
    """Write config, tracks.csv, meshes, maps and plots into ``tmp``; returns the ``files``
    section. ``ranked`` are the report's track dicts in severity order; ``report_stub`` holds
    the report's ``layers`` and ``realtime`` (for the alarm marks)."""
    def step(name, done, total):
        if stage is not None:
            stage(name, done, total)

    files: dict[str, list[str]] = {"meshes": [], "deviation_maps": [], "track_plots": [],
                                   "reference": [], "figures": []}
    if config_toml is not None:
        (tmp / "config.toml").write_text(config_toml, encoding="utf-8")
    write_tracks_csv(tmp / "tracks.csv", tracks)
    for sub in ("meshes", "maps", "plots"):
        (tmp / sub).mkdir()
    for k, r in enumerate(results):
        step("meshes", k, len(results))
        name = f"meshes/layer_{r.layer:03d}.ply"
        write_deviation_ply(tmp / name, r.deviation, limit_mm)
        files["meshes"].append(name)
    if results:
        name = f"meshes/reference_layer_{results[-1].layer:03d}.stl"
        write_reference_stl(tmp / name, results[-1].reference)
        files["reference"].append(name)
    by_layer = {r.layer: r for r in results}
    if map_layers is None:
        map_layers = default_map_layers(list(by_layer), ranked)
    kinds = {t["id"]: t["kind"] for t in ranked}
    for k, layer in enumerate(map_layers):
        step("deviation maps", k, len(map_layers))
        r = by_layer.get(layer)
        if r is None:
            raise ValueError(f"write_report: no result for requested map layer {layer}")
        marks = layer_markers(r, kinds)
        name = f"maps/deviation_layer_{layer:03d}.png"
        plot_deviation_map(tmp / name, r.deviation, marks, limit_mm, outline=outline)
        files["deviation_maps"].append(name)
    step("overview and timeline", 0, 2)
    if results:
        last = results[-1]
        marks = [(t["id"], t["kind"], summary.location_mm(t)) for t in ranked[:MARKED_TRACKS]]
        plot_deviation_map(tmp / "plots/overview.png", last.deviation, marks, limit_mm,
                           outline=outline, dpi=120,
                           title=f"Layer {last.layer} (last): deviation, planned outline "
                                 "dashed, tracks numbered")
        files["figures"].append("plots/overview.png")
    step("overview and timeline", 1, 2)
    rows = sorted(ranked[:TIMELINE_ROWS], key=lambda t: (t["first_layer"], t["id"]))
    alarms = (report_stub.get("realtime") or {}).get("alarms", [])
    layers_of = summary.alarm_layers(report_stub)
    marks = [(lay, summary.alarm_track(a, lay, ranked)) for a, lay in zip(alarms, layers_of,
                                                                        strict=True)]
    plot_timeline(tmp / "plots/timeline.png", rows, marks, n_layers=len(results))
    files["figures"].append("plots/timeline.png")
    step("track plots", 0, 1)
    items = [(f"plots/track_{t['id']:03d}_{t['kind']}.svg", t) for t in ranked[:PLOTTED_TRACKS]]
    write_track_svgs([(tmp / name, t) for name, t in items], KIND_COLOURS)
    files["track_plots"] += [name for name, _ in items]
    return files


def layer_markers(result, kinds: dict[int, str]) -> list[tuple[int, str, tuple[float, float]]]:
    """``(track_id, kind, (x, y))`` of a layer's tracked regions, the first
    :data:`MAP_MARKERS`: a region no track holds (not yet confirmed, or not evidence enough)
    is coloured on the map but gets no number, as nothing in the table answers to it."""
    pairs = [(reg, tid) for reg, tid in zip(result.regions, result.track_ids, strict=True)
             if tid is not None]
    return [(int(tid), kinds.get(tid, reg.kind), tuple(reg.centroid_O[:2]))
            for reg, tid in pairs[:MAP_MARKERS]]
