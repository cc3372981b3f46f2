"""report.json (schema-versioned), tracks.csv and the comparison with injected-fault truth."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from dm2.defects.track import Track

# 2: a track's and a region's ``height_mm`` is the largest |deviation| from the reference (was
# the z extent of the region's box, now ``box_extent_z_mm``); ``trend`` is judged on that height
REPORT_SCHEMA = "dm2.report/2"
DEFECT_MIN_HEIGHT_MM = 0.5  # a fault's onset: its first layer whose truth reaches this
# which track kind an injected fault is expected to produce (sign of the fault's effect)
_FAULT_KIND = {"bump": "overbuild", "dent": "underbuild", "corner_dwell": "overbuild",
               "clog": "underbuild", "feed_drop": "underbuild"}


def _clean(obj):
    """JSON-safe copy: numpy to Python, non-finite floats to None."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    if isinstance(obj, np.integer | np.bool_):
        return obj.item()
    if isinstance(obj, float | np.floating):
        return float(obj) if math.isfinite(obj) else None
    return obj


def expected_kind(fault: dict) -> str | None:
    """The track kind a fault entry should produce, or None where the sign is not implied."""
    sign = fault.get("sign")
    if sign is not None and sign != 0:
        return "overbuild" if sign > 0 else "underbuild"
    kind = fault.get("kind")
    if kind in _FAULT_KIND:
        return _FAULT_KIND[kind]
    factor = fault.get("factor")
    if kind in ("feed_step", "feed_drift") and factor is not None:
        return "overbuild" if factor > 1 else "underbuild"
    if kind == "efficiency_drift":
        per = fault.get("per_layer", fault.get("factor"))
        return None if per is None else ("overbuild" if per > 0 else "underbuild")
    return fault.get("expected_kind")


def _track_near(track: Track, xy, within_mm: float) -> float:
    """Smallest xy distance [mm] from ``xy`` to the track's centroids; inf if none."""
    c = np.array([h["centroid_O_mm"][:2] for h in track.history])
    return float(np.min(np.linalg.norm(c - np.asarray(xy, float), axis=1))) if len(c) else np.inf


def _fault_distance(track: Track, fault: dict, within_mm: float) -> float:
    """xy distance [mm] from a track to a fault's location (0 inside its box; 0 if global)."""
    region = fault.get("region_O") or {}
    dists = []
    if region.get("bbox"):
        x0, y0, x1, y1 = region["bbox"]
        for h in track.history:
            cx, cy = h["centroid_O_mm"][:2]
            dists.append(float(np.hypot(max(x0 - cx, 0, cx - x1), max(y0 - cy, 0, cy - y1))))
    for c in region.get("centers") or []:
        dists.append(_track_near(track, c, within_mm))
    if fault.get("center_O_mm"):
        dists.append(_track_near(track, fault["center_O_mm"][:2], within_mm))
    return min(dists) if dists else 0.0


def _first_layer(fault: dict):
    layers = fault.get("layers")
    return min(layers) if layers else None


def truth_onset_layer(fault: dict):
    """The first layer whose truth deviation (``deviation_by_layer_mm``, the twin's peak for a
    local fault, median for a global one) reaches ``DEFECT_MIN_HEIGHT_MM`` with the fault's
    sign, or None (no per-layer truth, or it never does): a monitor can only be asked to see
    a fault from there on."""
    by_layer = fault.get("deviation_by_layer_mm") or {}
    sign = fault.get("sign") or 1
    for k in sorted(by_layer, key=int):
        if sign * by_layer[k] >= DEFECT_MIN_HEIGHT_MM:
            return int(k)
    return None


def compare_with_truth(tracks: list[Track], faults: list[dict], within_mm: float = 10.0) -> list:
    """For each injected fault: whether a track of the expected kind explains it.

    A fault entry is a dict as twin.world.truth writes it (``kind``, ``sign``, ``layers``,
    ``region_O`` with ``bbox`` / ``centers``) or a scenario-style fault (``kind``,
    ``center_O_mm``, ``layers`` [first, last], ``factor``). A track matches when its kind
    family equals the expected one (global or local), it lasts to the fault's first layer or
    beyond, and for located faults it comes within ``within_mm`` of the fault's region.
    """
    out = []
    for f in faults:
        want = expected_kind(f)
        first, onset = _first_layer(f), truth_onset_layer(f)
        best, best_d = None, np.inf
        for t in tracks:
            if want is not None and t.kind.replace("local_", "") != want:
                continue
            if first is not None and t.last_layer < first:
                continue
            d = _fault_distance(t, f, within_mm)
            if d <= within_mm and d < best_d:
                best, best_d = t, d
        out.append({"fault": f, "expected_kind": want, "detected": best is not None,
                    "track_id": None if best is None else best.id,
                    "distance_mm": None if best is None else best_d,
                    "first_layer_detected": None if best is None else best.first_layer,
                    "detection_delay_layers": None if best is None or first is None
                    else best.first_layer - first,
                    "truth_onset_layer": onset,
                    "onset_delay_layers": None if best is None or onset is None
                    else best.first_layer - onset})
    return out


def _matching(tracks: list[Track], e) -> list[Track]:
    """The tracks of expectation ``e``'s kind, seen up to ``e.from_layer`` or later, within
    ``e.within_mm`` of ``e.near_mm`` (each only where given)."""
    return [t for t in tracks if t.kind == e.kind
            and (e.from_layer is None or t.last_layer >= e.from_layer)
            and (e.near_mm is None or _track_near(t, e.near_mm, e.within_mm) <= e.within_mm)]


FINDING_SIGN = {"overbuild": 1, "underbuild": -1}  # the global kinds a process finding reports


def check_expectations(tracks: list[Track], expect, findings=()) -> list[dict]:
    """Hold the tracks to a scenario's ``[expect]`` section; one result per expectation.

    ``no_tracks`` concerns global over/underbuild tracks: local deviations are allowed
    individually (paper sec. 6) and reported as early warnings; ``no_local_tracks`` holds
    those to zero as well.

    ``findings`` are the run's process findings (report.json ``process.finding_details``). A
    finding reports a global over- or underbuild of the whole part, from its ``since_layer`` to
    the end of the run, so an expected global ``overbuild`` (``underbuild``) track is also met
    by a finding of sign +1 (-1), wherever the expectation places it; the result names the
    findings in ``findings``. Local kinds and the ``absent`` and ``no_tracks`` checks concern
    tracks only (a finding is scored on its own by the bench).
    """
    results = []
    for e in expect.tracks:
        hits = _matching(tracks, e)
        found = [f["text"] for f in findings
                 if e.kind in FINDING_SIGN and int(f["sign"]) == FINDING_SIGN[e.kind]]
        res = {"expect": f"{e.kind} track" + (f" near {list(e.near_mm)}" if e.near_mm else ""),
               "passed": bool(hits or found), "track_ids": [t.id for t in hits]}
        if found:
            res["findings"] = found
        results.append(res)
    for e in getattr(expect, "absent", ()):
        hits = _matching(tracks, e)
        results.append({"expect": f"no {e.kind} track" + (f" near {list(e.near_mm)}" if e.near_mm
                                                           else ""),
                        "passed": not hits, "track_ids": [t.id for t in hits]})
    if expect.no_tracks:
        hits = [t.id for t in tracks if not t.kind.startswith("local_")]
        results.append({"expect": "no overbuild/underbuild tracks", "passed": not hits,
                        "track_ids": hits})
    if getattr(expect, "no_local_tracks", False):
        hits = [t.id for t in tracks if t.kind.startswith("local_")]
        results.append({"expect": "no local overbuild/underbuild tracks", "passed": not hits,
                        "track_ids": hits})
    return results


def _heights(entry: dict) -> dict:
    """A region or history entry with ``height_mm`` = its largest |deviation| from the
    reference and the z extent of its box (region and reference beneath) as
    ``box_extent_z_mm``."""
    out = dict(entry)
    out["box_extent_z_mm"] = entry["height_mm"]
    out["height_mm"] = abs(entry["max_deviation_mm"])
    return out


def _with_height_rates(history: list[dict]) -> list[dict]:
    """``height_rate_mm_per_layer`` of the height of :func:`_heights`; the box extent's rate
    becomes ``box_extent_z_rate_mm_per_layer``."""
    for prev, h in zip([None] + history[:-1], history, strict=True):
        h["box_extent_z_rate_mm_per_layer"] = h.get("height_rate_mm_per_layer", 0.0)
        h["height_rate_mm_per_layer"] = 0.0 if prev is None else (
            (h["height_mm"] - prev["height_mm"]) / max(h["layer"] - prev["layer"], 1))
    return history


def report_track(track: Track) -> dict:
    """report.json's view of a track: its dict with heights as in :func:`_heights` (history and
    the per-layer ``height_mm`` map), ``box_extent_z_mm`` per layer, the trend judged on that
    height, and ``peak_deviation_mm`` (signed), ``peak_area_mm2``, ``height_slope_mm_per_layer``,
    ``severity_mm3`` (see dm2.report.summary)."""
    from dm2.report import summary

    d = track.to_dict()
    d["history"] = _with_height_rates([_heights(h) for h in track.history])
    d["height_mm"] = {str(h["layer"]): h["height_mm"] for h in d["history"]}
    d["box_extent_z_mm"] = {str(h["layer"]): h["box_extent_z_mm"] for h in d["history"]}
    d["trend"] = summary.trend(d)
    d.update(peak_deviation_mm=summary.peak_deviation_mm(d),
             peak_area_mm2=summary.peak_area_mm2(d),
             height_slope_mm_per_layer=summary.height_slope_mm_per_layer(d),
             severity_mm3=summary.severity(d))
    return d


def build_report(results, tracks: list[Track], *, dropped: dict | None = None,
                 timing: dict | None = None, fault_truth: dict | list | None = None,
                 expect=None, files: dict | None = None, meta: dict | None = None,
                 sections: dict | None = None) -> dict:
    """The report.json content (top-level: schema, meta, layers, tracks, dropped, timing, ...).

    ``results`` is a list of dm2.defects.layer_analysis.LayerResult; ``fault_truth`` a dict with
    ``faults``
    (or a list of fault dicts) as written by the twin.
    """
    layers = []
    for r in results:
        layers.append({"layer": r.layer, "stamp_s": r.deviation.stamp_s,
                       "statistics": r.statistics(), "timing_s": r.timing_s,
                       "regions": [{**_heights(reg.to_dict()), "track_id": tid}
                                   for reg, tid in zip(r.regions, r.track_ids, strict=True)]})
    doc = {"schema": REPORT_SCHEMA, "meta": meta or {}, "layers": layers,
           "tracks": [report_track(t) for t in tracks], "dropped": dict(dropped or {}),
           "timing": dict(timing or {}), "files": files or {}}
    for key, value in (sections or {}).items():
        if key in doc:
            raise ValueError(f"build_report: section {key!r} would replace a core section")
        doc[key] = value
    if fault_truth is not None:
        faults = fault_truth.get("faults", []) if isinstance(fault_truth, dict) else fault_truth
        doc["fault_truth"] = compare_with_truth(tracks, list(faults))
    if expect is not None:
        findings = ((sections or {}).get("process") or {}).get("finding_details") or ()
        doc["expectations"] = check_expectations(tracks, expect, findings)
    return _clean(doc)


TRACK_CSV_FIELDS = ("track_id", "kind", "layer", "state", "area_mm2", "height_mm",
                    "box_extent_z_mm", "max_deviation_mm", "mean_deviation_mm", "centroid_x_mm",
                    "centroid_y_mm", "area_rate_mm2_per_layer", "height_rate_mm_per_layer", "trend")


def write_tracks_csv(path: str | Path, tracks: list[Track]) -> None:
    """One row per track and layer; ``height_mm`` is the largest |deviation| from the
    reference, ``box_extent_z_mm`` the z extent of the region's box."""
    from dm2.report.summary import trend as report_trend

    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(TRACK_CSV_FIELDS)
        for t in tracks:
            trend = report_trend({"history": t.history})
            for h in _with_height_rates([_heights(h) for h in t.history]):
                w.writerow([t.id, t.kind, h["layer"], h["state"], f"{h['area_mm2']:.4f}",
                            f"{h['height_mm']:.4f}", f"{h['box_extent_z_mm']:.4f}",
                            f"{h['max_deviation_mm']:.4f}", f"{h['mean_deviation_mm']:.4f}",
                            f"{h['centroid_O_mm'][0]:.3f}",
                            f"{h['centroid_O_mm'][1]:.3f}", f"{h['area_rate_mm2_per_layer']:.4f}",
                            f"{h['height_rate_mm_per_layer']:.4f}", trend])
