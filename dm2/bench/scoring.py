"""Score a monitoring run's report against the twin's fault truth (pure: dicts in, dicts out).

Inputs are the run's ``report.json`` content (tracks, per-layer regions with their track ids
and boxes, layer stamps, expectations), the twin's ``faults.json`` content and the scenario's
fault settings; nothing here imports the twin.

Definitions
-----------
fault height per layer ``h_L``
    ``sign * deviation_by_layer_mm[L]`` from the truth: how far the fault moved the true
    surface from the fault-free run with the same seed, positive in the fault's direction.
qualifying defect (the population of F1)
    a truth fault whose largest ``h_L`` is at least :data:`DEFECT_MIN_HEIGHT_MM` (0.5 mm) and
    whose footprint at that height is at least :data:`DEFECT_MIN_AREA_MM2` (4 mm^2). The
    footprint is the disc where a Gaussian of that peak exceeds 0.5 mm for local faults (bump
    and dent: the blob's own width; corner dwell: the plume's sigma) and the truth region's box
    for global faults (feed, clog, efficiency, standoff act over the whole part).
onset layer
    the first layer with ``h_L >= DEFECT_MIN_HEIGHT_MM``; the onset delay is the first layer
    of a matching track minus that (negative: flagged before it reached 0.5 mm), in layers and
    in process seconds between the two layers' closing stamps.
matching track
    a track (global or local kind) active at or after the fault's first affected layer whose
    region boxes come within :data:`MATCH_MARGIN_MM` of the truth region box in xy. The fault
    is *detected* when a matching track has the fault's sign (``detected_global`` when one of
    those is a global over/underbuild track); ``sign_ok`` says whether the largest matching
    track (by peak area) has it.
false-positive track
    a global (over/underbuild) track that matches no truth fault of its sign. Unmatched local
    tracks are counted separately as early warnings (the paper allows them individually).
IoU, area and height error
    at the last layer: the xy box of the matching regions against the truth region box (for
    bump and dent the disc where the blob exceeds the monitor's ``delta_global_mm``); their
    summed area against the truth footprint (the truth's ``area_mm2_by_layer`` where the twin
    reports it, else the estimate above at ``delta_global_mm``); their largest |deviation|
    against ``|h_L|``.
"""

from __future__ import annotations

import math

import numpy as np

DEFECT_MIN_HEIGHT_MM = 0.5
DEFECT_MIN_AREA_MM2 = 4.0
MATCH_MARGIN_MM = 2.0
GLOBAL_KINDS = ("overbuild", "underbuild")
LOCAL_FAULTS = ("bump", "dent", "corner_dwell")
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


def track_sign(kind: str) -> int:
    """+1 for (local) overbuild, -1 for (local) underbuild."""
    return 1 if kind.replace("local_", "") == "overbuild" else -1


def gaussian_radius_mm(peak_mm: float, sigma_mm: float, level_mm: float) -> float:
    """Radius [mm] where a Gaussian of ``peak_mm`` and ``sigma_mm`` falls to ``level_mm``."""
    if peak_mm <= level_mm or sigma_mm <= 0:
        return 0.0
    return float(sigma_mm * math.sqrt(2.0 * math.log(peak_mm / level_mm)))


def fault_heights(fault: dict) -> dict[int, float]:
    """``h_L`` per layer [mm], positive in the direction of the fault's sign."""
    sign = fault.get("sign") or 1
    return {int(k): sign * float(v) for k, v in
            (fault.get("deviation_by_layer_mm") or {}).items() if v is not None}


def _fault_sigma_mm(fault: dict, config: dict | None, plume_sigma_mm: float) -> float:
    if fault["kind"] in ("bump", "dent") and config and config.get("width_mm"):
        return float(config["width_mm"]) / FWHM_PER_SIGMA
    return plume_sigma_mm


def _box_area(box) -> float:
    return max(box[2] - box[0], 0.0) * max(box[3] - box[1], 0.0)


def footprint_mm2(fault: dict, peak_mm: float, config: dict | None, plume_sigma_mm: float,
                  level_mm: float) -> float:
    """Area [mm^2] where the fault exceeds ``level_mm`` (see the module's definitions)."""
    if fault["kind"] in LOCAL_FAULTS:
        r = gaussian_radius_mm(peak_mm, _fault_sigma_mm(fault, config, plume_sigma_mm),
                               level_mm)
        n = max(len((fault.get("region_O") or {}).get("centers") or []), 1)
        return n * math.pi * r * r
    return _box_area((fault.get("region_O") or {}).get("bbox") or (0, 0, 0, 0))


def truth_box(fault: dict, peak_mm: float, config: dict | None, plume_sigma_mm: float,
              level_mm: float) -> list[float]:
    """The truth region's xy box [xmin, ymin, xmax, ymax] [mm] used for matching and IoU."""
    region = fault.get("region_O") or {}
    if fault["kind"] in ("bump", "dent") and region.get("centers"):
        r = max(gaussian_radius_mm(peak_mm, _fault_sigma_mm(fault, config, plume_sigma_mm),
                                   level_mm), 0.5)
        c = np.asarray(region["centers"], float)
        return [float(c[:, 0].min() - r), float(c[:, 1].min() - r),
                float(c[:, 0].max() + r), float(c[:, 1].max() + r)]
    return [float(v) for v in region.get("bbox") or (0.0, 0.0, 0.0, 0.0)]


def iou_xy(a, b) -> float:
    """Intersection over union of two xy boxes [xmin, ymin, xmax, ymax]."""
    ix = max(min(a[2], b[2]) - max(a[0], b[0]), 0.0)
    iy = max(min(a[3], b[3]) - max(a[1], b[1]), 0.0)
    inter = ix * iy
    union = _box_area(a) + _box_area(b) - inter
    return float(inter / union) if union > 0 else 0.0


def _boxes_touch(a, b, margin: float) -> bool:
    return (a[0] <= b[2] + margin and b[0] <= a[2] + margin
            and a[1] <= b[3] + margin and b[1] <= a[3] + margin)


def regions_by_track(report: dict) -> dict[int, list[dict]]:
    """Each track id's regions over the layers (with ``layer`` and the xy ``box``)."""
    out: dict[int, list[dict]] = {}
    for layer in report.get("layers", []):
        for reg in layer.get("regions", []):
            if reg.get("track_id") is None:
                continue
            box = [reg["bbox_min_O_mm"][0], reg["bbox_min_O_mm"][1],
                   reg["bbox_max_O_mm"][0], reg["bbox_max_O_mm"][1]]
            out.setdefault(int(reg["track_id"]), []).append({**reg, "layer": layer["layer"],
                                                             "box": box})
    return out


def score_fault(fault: dict, report: dict, *, config: dict | None = None,
                plume_sigma_mm: float = 2.0, delta_mm: float = 0.4,
                regions: dict[int, list[dict]] | None = None) -> dict:
    """Score one truth fault against the run's tracks (see the module's definitions)."""
    regions = regions_by_track(report) if regions is None else regions
    tracks = {int(t["id"]): t for t in report.get("tracks", [])}
    stamps = {int(ly["layer"]): ly.get("stamp_s") for ly in report.get("layers", [])}
    h = fault_heights(fault)
    peak = max(h.values(), default=0.0)
    onset = min((k for k, v in h.items() if v >= DEFECT_MIN_HEIGHT_MM), default=None)
    first_affected = min(fault.get("layers") or [onset if onset is not None else 0])
    area_at_min = footprint_mm2(fault, peak, config, plume_sigma_mm, DEFECT_MIN_HEIGHT_MM)
    qualifies = peak >= DEFECT_MIN_HEIGHT_MM and area_at_min >= DEFECT_MIN_AREA_MM2
    box = truth_box(fault, peak, config, plume_sigma_mm, delta_mm)
    sign = int(fault.get("sign") or 1)

    matched: list[int] = []
    for tid, regs in regions.items():
        regs = [r for r in regs if r["layer"] >= first_affected]
        if regs and any(_boxes_touch(r["box"], box, MATCH_MARGIN_MM) for r in regs):
            matched.append(tid)
    right = [t for t in matched if track_sign(tracks[t]["kind"]) == sign]
    primary = max(matched, key=lambda t: max(r["area_mm2"] for r in regions[t]), default=None)
    out = {"fault_id": fault.get("id"), "kind": fault["kind"], "sign": sign,
           "peak_height_mm": peak, "qualifies": bool(qualifies), "onset_layer": onset,
           "detected": bool(right),
           "detected_global": any(tracks[t]["kind"] in GLOBAL_KINDS for t in right),
           "sign_ok": primary is not None
           and track_sign(tracks[primary]["kind"]) == sign,
           "track_ids": sorted(right), "first_layer_detected": None,
           "onset_delay_layers": None, "onset_delay_s": None, "iou": None,
           "area_mm2": None, "truth_area_mm2": footprint_mm2(fault, peak, config,
                                                               plume_sigma_mm, delta_mm),
           "area_error_mm2": None, "height_mm": None, "truth_height_mm": None,
           "height_error_mm": None}
    if not right:
        return out
    detected_at = min(min(r["layer"] for r in regions[t] if r["layer"] >= first_affected)
                      for t in right)
    out["first_layer_detected"] = detected_at
    if onset is not None:
        out["onset_delay_layers"] = detected_at - onset
        if stamps.get(detected_at) is not None and stamps.get(onset) is not None:
            out["onset_delay_s"] = float(stamps[detected_at] - stamps[onset])
    last = max(r["layer"] for t in right for r in regions[t])
    final = [r for t in right for r in regions[t] if r["layer"] == last
             and _boxes_touch(r["box"], box, MATCH_MARGIN_MM)]
    if final:
        union = [min(r["box"][0] for r in final), min(r["box"][1] for r in final),
                 max(r["box"][2] for r in final), max(r["box"][3] for r in final)]
        area = float(sum(r["area_mm2"] for r in final))
        height = float(max(abs(r["max_deviation_mm"]) for r in final))
        truth_h = abs(h.get(last, peak))
        measured_area = (fault.get("area_mm2_by_layer") or {}).get(str(last))
        if measured_area is not None:  # the truth's own area beyond the monitor's tolerance
            out["truth_area_mm2"] = float(measured_area)
        out.update(iou=iou_xy(union, box), area_mm2=area,
                   area_error_mm2=area - out["truth_area_mm2"], height_mm=height,
                   truth_height_mm=truth_h, height_error_mm=height - truth_h)
    return out


def score_run(report: dict, fault_truth: dict | None, *, fault_configs: list[dict] = (),
              plume_sigma_mm: float = 2.0, delta_mm: float = 0.4,
              reconstruction: dict | None = None, process_s: float | None = None,
              monitor_s: float | None = None, wall_s: float | None = None) -> dict:
    """Score one scenario run: per-fault scores, false-positive tracks, expectations, speed.

    Parameters
    ----------
    report : report.json content
    fault_truth : faults.json content (``{"faults": [...]}``) or None (no faults)
    fault_configs : the scenario's ``[[faults]]`` as dicts, index = truth ``id``
    plume_sigma_mm : the process plume's sigma [mm] (corner-dwell footprints)
    delta_mm : the monitor's global threshold [mm] (truth boxes of blobs)
    reconstruction : per layer ``{"rms_mm": ...}`` (measured surface vs true surface)
    process_s, monitor_s, wall_s : process seconds simulated, pipeline and total wall seconds
    """
    faults = list((fault_truth or {}).get("faults", []))
    regions = regions_by_track(report)
    scores = []
    for f in faults:
        cfg = fault_configs[f["id"]] if f.get("id") is not None and \
            f["id"] < len(fault_configs) else None
        scores.append(score_fault(f, report, config=cfg, plume_sigma_mm=plume_sigma_mm,
                                  delta_mm=delta_mm, regions=regions))
    explained = {t for s in scores for t in s["track_ids"]}
    fp = [int(t["id"]) for t in report.get("tracks", [])
          if t["kind"] in GLOBAL_KINDS and int(t["id"]) not in explained]
    warnings = [int(t["id"]) for t in report.get("tracks", [])
                if t["kind"] not in GLOBAL_KINDS and int(t["id"]) not in explained]
    expectations = report.get("expectations", [])
    rms = [v["rms_mm"] for v in (reconstruction or {}).values()]
    return {"faults": scores, "false_positive_tracks": fp, "unmatched_local_tracks": warnings,
            "expectations": expectations,
            "expect_passed": all(e.get("passed") for e in expectations),
            "layers": len(report.get("layers", [])),
            "reconstruction_rms_mm": float(np.sqrt(np.mean(np.square(rms)))) if rms else None,
            "reconstruction_by_layer": {str(k): v for k, v in (reconstruction or {}).items()},
            "process_s": process_s, "monitor_s": monitor_s, "wall_s": wall_s,
            "realtime_factor": process_s / monitor_s if process_s and monitor_s else None,
            "realtime_factor_with_twin": process_s / wall_s if process_s and wall_s else None}


def summarize(runs: dict[str, dict], targets: dict | None = None) -> dict:
    """Suite totals: F1 over qualifying defects, worst onset delay, false positives, targets.

    ``runs`` maps scenario name -> :func:`score_run` result. ``targets`` may hold ``f1_min``,
    ``max_onset_delay_layers`` and ``max_false_positive_tracks`` (each checked if present).
    """
    qual = [f for r in runs.values() for f in r["faults"] if f["qualifies"]]
    tp = sum(1 for f in qual if f["detected"] and f["sign_ok"])
    fn = len(qual) - tp
    fp = sum(len(r["false_positive_tracks"]) for r in runs.values())
    precision = tp / (tp + fp) if tp + fp else 1.0
    recall = tp / (tp + fn) if tp + fn else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    delays = [f["onset_delay_layers"] for f in qual if f["onset_delay_layers"] is not None]
    out = {"qualifying_defects": len(qual), "true_positives": tp, "false_negatives": fn,
           "false_positive_tracks": fp, "precision": precision, "recall": recall, "f1": f1,
           "max_onset_delay_layers": max(delays) if delays else None,
           "expectations_passed": all(r["expect_passed"] for r in runs.values()),
           "definition": f"defects >= {DEFECT_MIN_HEIGHT_MM} mm high and >= "
                         f"{DEFECT_MIN_AREA_MM2} mm2 (see dm2.bench.scoring)"}
    checks = {}
    targets = targets or {}
    if "f1_min" in targets:
        checks["f1"] = f1 >= targets["f1_min"]
    if "max_onset_delay_layers" in targets:
        checks["onset"] = all(d <= targets["max_onset_delay_layers"] for d in delays)
    if "max_false_positive_tracks" in targets:
        checks["false_positives"] = fp <= targets["max_false_positive_tracks"]
    out["targets"] = dict(targets)
    out["target_checks"] = checks
    out["passed"] = out["expectations_passed"] and all(checks.values())
    return out
