"""What a run found, from the monitor's own outputs: severity order, verdict sentences, alarms.

Everything here reads the report dict's ``tracks``, ``layers`` and ``realtime`` sections only,
never ``fault_truth`` or ``expectations``, so the verdict is the same with or without the twin's
truth beside the run.

A track's *height* is its largest deviation from the reference (the signed value of largest
magnitude, ``max_deviation_mm``, over its layers); the z extent of a region's box is
``box_extent_z_mm``. Defects are the global over/underbuild tracks; local over/underbuild
tracks are early warnings, counted as *uncertain* regions in the verdict (paper sec. 6 allows
local deviations individually).

Severity: defects before local tracks, then by peak ``|height| x peak area`` [mm^3] (a
deviation volume scale), then by first layer.
"""

from __future__ import annotations

import numpy as np

from dm2.core.tolerances import RATIO_FLOOR

VERDICT_SENTENCES = 5  # defect tracks named in the verdict; the rest are in the table
TREND_SLOPE_MM = 0.02  # [mm/layer] height slope beyond which a track grows or shrinks
TREND_AREA_REL = 0.05  # relative area slope per layer beyond which it grows or shrinks


def is_defect(track: dict) -> bool:
    return not str(track["kind"]).startswith("local_")


def kind_label(kind: str) -> str:
    """``local_overbuild`` -> ``Local overbuild``."""
    return kind.replace("_", " ").capitalize()


def peak_deviation_mm(track: dict) -> float:
    """The signed deviation of largest magnitude over the track's history [mm]."""
    devs = [h["max_deviation_mm"] for h in track["history"]]
    return float(devs[int(np.argmax(np.abs(devs)))]) if devs else 0.0


def peak_area_mm2(track: dict) -> float:
    return float(max((h["area_mm2"] for h in track["history"]), default=0.0))


def height_slope_mm_per_layer(track: dict) -> float:
    """Least-squares slope of ``|max deviation|`` against layer (0 with one layer) [mm/layer]."""
    hist = track["history"]
    if len(hist) < 2:
        return 0.0
    layers = np.array([h["layer"] for h in hist], float)
    height = np.abs([h["max_deviation_mm"] for h in hist])
    return float(np.polyfit(layers, height, 1)[0])


def trend(track: dict) -> str:
    """``amplifying`` / ``self-compensating`` / ``stable`` from the height (max |deviation|)
    slope, else from the relative area slope (the rule of dm2.defects.track.Track.trend)."""
    hist = track["history"]
    if len(hist) < 2:
        return "stable"
    h_slope = height_slope_mm_per_layer(track)
    layers = np.array([h["layer"] for h in hist], float)
    area = np.array([h["area_mm2"] for h in hist])
    a_slope = np.polyfit(layers, area, 1)[0] / max(area.mean(), RATIO_FLOOR)
    if h_slope > TREND_SLOPE_MM or (abs(h_slope) <= TREND_SLOPE_MM and a_slope > TREND_AREA_REL):
        return "amplifying"
    if h_slope < -TREND_SLOPE_MM or (abs(h_slope) <= TREND_SLOPE_MM
                                     and a_slope < -TREND_AREA_REL):
        return "self-compensating"
    return "stable"


def severity(track: dict) -> float:
    """Peak ``|height| x peak area`` [mm^3]."""
    return abs(peak_deviation_mm(track)) * peak_area_mm2(track)


def by_severity(tracks: list[dict]) -> list[dict]:
    """Tracks in order of severity (see the module docstring)."""
    return sorted(tracks, key=lambda t: (not is_defect(t), -severity(t), t["first_layer"],
                                         t["id"]))


def location_mm(track: dict) -> tuple[float, float]:
    """xy centroid [mm] of the track's last observation."""
    c = track["history"][-1]["centroid_O_mm"] if track["history"] else (np.nan, np.nan)
    return float(c[0]), float(c[1])


def trend_phrase(track: dict) -> str:
    if len(track["history"]) < 2:
        return f"seen in layer {track['first_layer']} only"
    slope = height_slope_mm_per_layer(track)
    t = trend(track)
    if t == "amplifying":
        return f"growing {abs(slope):.2f} mm/layer" if slope > TREND_SLOPE_MM else \
            "growing in area"
    if t == "self-compensating":
        return f"shrinking {abs(slope):.2f} mm/layer" if slope < -TREND_SLOPE_MM else \
            "shrinking in area"
    return "stable"


def track_sentence(track: dict) -> str:
    """E.g. ``Overbuild at (77.6, 59.3) mm, from layer 3, 26 mm², +0.95 mm, growing 0.20
    mm/layer``."""
    x, y = location_mm(track)
    span = (f"from layer {track['first_layer']}" if track["last_layer"] == track["first_layer"]
            else f"from layer {track['first_layer']} to {track['last_layer']}")
    return (f"{kind_label(track['kind'])} at ({x:.1f}, {y:.1f}) mm, {span}, "
            f"{peak_area_mm2(track):.0f} mm², {peak_deviation_mm(track):+.2f} mm, "
            f"{trend_phrase(track)} (track {track['id']})")


MODEL_FINDING_FACTOR = 1.5  # a model-error term raised this much is said in the verdict
MODEL_TERM_PLACES = {"wall": "on walls", "edge": "at the reference's edges and corners",
                     "foot": "at the foot of walls",
                     "plume_concave": "where the part is concave (wall feet, rims, holes)",
                     "plume_convex": "where the part is convex (edges, ridges)"}


def model_findings(report: dict) -> list[str]:
    """Where the layers raised the uncertainty's model-error terms
    (dm2.defects.uncertainty_online) by :data:`MODEL_FINDING_FACTOR` or more: the cell departs
    from the monitor's deposition model there, so a defect there must stand out further, e.g.
    "the deposit departs from the model where the part is convex (edges, ridges): its bound
    raised up to 2.6x from layer 2"."""
    out = []
    for term, place in MODEL_TERM_PLACES.items():
        seen = [(lay.get("layer"), (lay.get("statistics") or {}).get("uncertainty_inflation",
                                                                     {}).get(term, 1.0))
                for lay in report.get("layers", [])]
        raised = [(layer, f) for layer, f in seen if f >= MODEL_FINDING_FACTOR]
        if raised:
            out.append(f"the deposit departs from the model {place}: its bound raised up to "
                       f"{max(f for _, f in raised):.1f}x from layer {raised[0][0]}")
    return out


# a profiler whose points the pipeline rejected before fusion (dm2.fusion.point_filter) at this
# share or more is said in the verdict: 5x the realistic sensor preset's whole share (0.4 %)
SENSOR_FINDING_SHARE = 0.02


def sensor_findings(report: dict) -> list[str]:
    """The profilers that lost :data:`SENSOR_FINDING_SHARE` of their points or more to the
    point filter (report.json ``point_filter``), since the first layer that rejected that much
    and from which on the layers together did, e.g. "S2 rejected 14 % of its points since
    layer 30 as not surface (window dirty, or spatter on the line?)"."""
    pf = report.get("point_filter") or {}
    out = []
    for sid, s in (pf.get("by_sensor") or {}).items():
        if s.get("share", 0.0) < SENSOR_FINDING_SHARE:
            continue
        # since the first layer that rejected that much itself and from which on the layers
        # together did
        since, share = None, s["share"]
        layers = pf.get("by_layer") or []
        for k, lay in enumerate(layers):
            n, r = lay["points"].get(sid, 0), lay["rejected"].get(sid, 0)
            n_on = sum(la["points"].get(sid, 0) for la in layers[k:])
            r_on = sum(la["rejected"].get(sid, 0) for la in layers[k:])
            if n and r / n >= SENSOR_FINDING_SHARE and r_on / n_on >= SENSOR_FINDING_SHARE:
                since, share = lay["layer"], r_on / n_on
                break
        when = f" since layer {since}" if since is not None else ""
        out.append(f"{sid} rejected {100 * share:.0f} % of its points{when} as not surface "
                   "(window dirty, or spatter on the line?)")
    return out


def verdict(report: dict) -> dict:
    """``{"headline", "sentences", "more", "defects", "uncertain", "layers", "findings"}``: the
    verdict of a report dict, from its tracks, layers, process findings (what the
    reference's process fit absorbed, dm2.process.process_fit), model findings
    (:func:`model_findings`) and sensor findings (:func:`sensor_findings`) only."""
    findings = [f"Process finding: {f}." for f in
                (report.get("process") or {}).get("findings", [])]
    findings += [f"Model finding: {f}." for f in model_findings(report)]
    findings += [f"Sensor finding: {f}." for f in sensor_findings(report)]
    tracks = by_severity(report.get("tracks", []))
    defects = [t for t in tracks if is_defect(t)]
    uncertain = len(tracks) - len(defects)
    n_layers = len(report.get("layers", []))
    if not defects:
        headline = (f"No defect found in {n_layers} layer{'s' if n_layers != 1 else ''}; "
                    f"{uncertain} region{'s' if uncertain != 1 else ''} uncertain"
                    + (" (local deviations, listed below)" if uncertain else "") + ".")
        return {"headline": headline, "sentences": findings, "more": 0, "defects": 0,
                "uncertain": uncertain, "layers": n_layers, "findings": len(findings)}
    headline = (f"{len(defects)} defect track{'s' if len(defects) != 1 else ''} in {n_layers} "
                f"layer{'s' if n_layers != 1 else ''}"
                + (f"; {uncertain} further region{'s' if uncertain != 1 else ''} uncertain "
                   "(local deviations)" if uncertain else "") + ".")
    shown = defects[:VERDICT_SENTENCES]
    return {"headline": headline,
            "sentences": [track_sentence(t) + "." for t in shown] + findings,
            "more": len(defects) - len(shown), "defects": len(defects), "uncertain": uncertain,
            "layers": n_layers, "findings": len(findings)}


def alarm_layers(report: dict) -> list[int | None]:
    """The layer of each real-time alarm: the first layer whose end stamp is at or after it."""
    ends = [(lay["stamp_s"], lay["layer"]) for lay in report.get("layers", [])
            if lay.get("stamp_s") is not None]
    ends.sort()
    out = []
    for a in (report.get("realtime") or {}).get("alarms", []):
        layer = next((lay for s, lay in ends if s >= a["stamp_s"]), ends[-1][1] if ends else None)
        out.append(layer)
    return out


def alarm_track(alarm: dict, layer, tracks: list[dict], within_mm: float = 5.0):
    """Id of the track nearest to an alarm in its layer (or the next), within ``within_mm``."""
    best, best_d = None, within_mm
    ax, ay = alarm["centroid_xy_O_mm"]
    for t in tracks:
        for h in t["history"]:
            if layer is not None and h["layer"] not in (layer, layer + 1):
                continue
            d = float(np.hypot(h["centroid_O_mm"][0] - ax, h["centroid_O_mm"][1] - ay))
            if d <= best_d and (t["kind"].replace("local_", "") == alarm["kind"]
                                .replace("local_", "")):
                best, best_d = t["id"], d
    return best
