"""Strict scoring of a monitoring run against the twin's truth maps (pure: data in, dicts out).

Inputs: the run's ``report.json`` content (tracks; per layer its regions with track ids and
closing stamp; the real-time alarms), the twin's per-layer truth maps
(:mod:`dm2.bench.truth_maps`: the true fault-caused deviation, faulty minus fault-free surface
of the same seed and ``[twin_process]``), the footprint of every track in every layer (the xy
of its regions' vertices with their areas) and ``faults.json``. Nothing here imports the twin.

Definitions
-----------
truth area of sign ``s`` at level ``h`` in layer ``L``
    the cells of layer ``L``'s truth map where ``s * deviation >= h``, dilated by
    :data:`DILATION_MM` (1 mm). With several faults in one run, a local fault's (bump, dent,
    corner dwell) share of the map is the part within :data:`LOCAL_SUPPORT_MM` of its centres;
    a global fault's is the whole map.
event tolerance
    the run's own: ``[monitor] delta_global_mm`` (``score_run(event_tolerance_mm=...)``; without
    one, :data:`DEFECT_MIN_HEIGHT_MM`, 0.5 mm). The floor the bench can measure follows it.
qualifying fault (the population of recall)
    a fault whose truth area of either sign at the event tolerance, undilated, covers at least
    :data:`DEFECT_MIN_AREA_MM2` (4 mm^2) in some layer; its **onset** is the first such layer.
explains
    a track explains a fault when, in some layer from the fault's onset, at least
    :data:`EXPLAIN_FRACTION` (50 %) of the track's area in that layer lies within the fault's
    truth area of the *track's* sign at the event tolerance (dilated). A fault is
    **detected** when a track explains it. Every track counts, local or global.
fragment
    a further track explaining an already explained fault (the earliest, then the largest, is
    the fault's true track): neutral, counted.
neutral track
    a track explaining no fault of which at least 50 % of the area lies, in some layer, within
    the truth area of its sign at :data:`NEUTRAL_MIN_HEIGHT_MM` (0.2 mm, or the event tolerance
    when lower), dilated: it sits on a true fault-caused deviation between that and the event
    tolerance. Neither true nor false.
drift track
    a track explaining no fault and not neutral, where the truth confirms the deviation: in
    some layer the twin's true surface stands off the reference the run used, in the track's
    sign and by at least the run's event tolerance (``[monitor] delta_global_mm``), under at
    least :data:`dm2.bench.reconstruction.DRIFT_SHARE` (50 %) of the track's area there
    (``track_truth`` ``drift_share``, :func:`dm2.bench.reconstruction.truth_checks`). The
    whole part drifts off the plan there, no fault does: reported and counted (``drift_tracks``,
    ``drift_area_mm2``: the sum of their largest area in one layer), neither true nor false,
    on a control too. Its entry keeps ``drift_since_layer`` and ``drift_rate_mm_per_layer``.
false track
    every other track. The **false area** is the sum over false tracks of their largest area in
    one layer [mm^2]. Where the run measured each track's flagged vertices against the twin's
    true surface (``track_truth``), a false track whose vertices lie closer to the truth than
    half their deviation from the reference is listed in ``false_tracks_part_deviates``: the
    fault-free part itself stands off the reference there (the monitor's model differs from
    the twin's physics), as measured. It still counts as false.
precision, recall, F1
    precision over tracks: true / (true + false) tracks; recall over qualifying faults:
    detected / qualifying; F1 their harmonic mean (1 for an empty population).
real-time false alarm
    a real-time alarm whose centroid lies outside the truth area of its sign at the neutral
    level (0.2 mm, or the event tolerance when lower) of its
    layer and of the layer before (the layer is the first whose closing stamp is at or after
    the alarm). Reported per hour of process time.
process finding
    the run's report states the deposition scale off nominal (report.json ``process``
    ``finding_details``: kind, estimate, sign, first layer). It **detects** a global fault (not
    a bump, dent or corner dwell) of its sign when the finding's first layer is within one layer
    of the fault's onset or of the first layer the fault acts in (its window's start in the
    truth): a change found at the layer it began is found, though the part shows it only once
    its effect has grown to the event tolerance.
    Otherwise an ``offset`` finding (the cell's scale) is **correct** when its estimate is within
    :data:`FINDING_TOLERANCE` (3 %) of the scale the twin's ``[twin_process]`` deposits at
    (``expected_process_scale``), and any other finding is a **false finding**, counted with the
    false tracks.
control
    a run without faults: any track or false finding on it is false.
"""

from __future__ import annotations

import numpy as np

from dm2.bench.reconstruction import DRIFT_SHARE
from dm2.report.report_json import DEFECT_MIN_HEIGHT_MM  # the report's onset height too

DEFECT_MIN_AREA_MM2 = 4.0
NEUTRAL_MIN_HEIGHT_MM = 0.2
DILATION_MM = 1.0
EXPLAIN_FRACTION = 0.5
LOCAL_SUPPORT_MM = 10.0
GLOBAL_KINDS = ("overbuild", "underbuild")
LOCAL_FAULTS = ("bump", "dent", "corner_dwell")
FINDING_TOLERANCE = 0.03

Footprints = dict  # track id -> {layer: (xy_O (k, 2) [mm], area (k,) [mm^2])}


def track_sign(kind: str) -> int:
    """+1 for (local) overbuild, -1 for (local) underbuild."""
    return 1 if kind.replace("local_", "") == "overbuild" else -1


def footprints_from_regions(report: dict) -> Footprints:
    """Footprints from the regions' xy boxes alone (a grid of points over each box, uniform
    weights): for reports whose vertices are gone. Runs in process pass real footprints."""
    out: Footprints = {}
    for layer in report.get("layers", []):
        for reg in layer.get("regions", []):
            if reg.get("track_id") is None:
                continue
            (x0, y0), (x1, y1) = reg["bbox_min_O_mm"][:2], reg["bbox_max_O_mm"][:2]
            gx, gy = np.meshgrid(np.linspace(x0, x1, 9), np.linspace(y0, y1, 9))
            xy = np.column_stack([gx.ravel(), gy.ravel()])
            w = np.full(xy.shape[0], float(reg["area_mm2"]) / xy.shape[0])
            _add(out, int(reg["track_id"]), int(layer["layer"]), xy, w)
    return out


def _add(out: Footprints, tid: int, layer: int, xy, w) -> None:
    by_layer = out.setdefault(tid, {})
    if layer in by_layer:
        a, b = by_layer[layer]
        by_layer[layer] = (np.vstack([a, xy]), np.concatenate([b, w]))
    else:
        by_layer[layer] = (np.asarray(xy, np.float64), np.asarray(w, np.float64))


def _support(fault: dict, tmap, n_faults: int) -> np.ndarray | None:
    """The fault's share of the map (None: all of it)."""
    centers = (fault.get("region_O") or {}).get("centers") or []
    if n_faults < 2 or fault["kind"] not in LOCAL_FAULTS or not centers:
        return None
    ny, nx = tmap.deviation_mm.shape
    x = tmap.x0_mm + tmap.cell_mm * np.arange(nx)
    y = tmap.y0_mm + tmap.cell_mm * np.arange(ny)
    gx, gy = np.meshgrid(x, y)
    m = np.zeros((ny, nx), bool)
    for cx, cy in centers:
        m |= (gx - cx) ** 2 + (gy - cy) ** 2 <= LOCAL_SUPPORT_MM ** 2
    return m


def _restrict(mask, support):
    return mask if support is None else mask & support


def _fault_population(fault: dict, maps: dict, n_faults: int, level_mm: float) -> dict:
    """Peak height, onset and per-layer peak of one fault from the truth maps."""
    peak, onset, peaks = 0.0, None, {}
    for k in sorted(maps):
        tm = maps[k]
        sup = _support(fault, tm, n_faults)
        dev = tm.deviation_mm if sup is None else np.where(sup, tm.deviation_mm, 0.0)
        p = float(np.max(np.abs(dev))) if dev.size else 0.0
        peaks[k] = p
        peak = max(peak, p)
        if onset is None and max(tm.area_mm2(_restrict(tm.mask(s, level_mm), sup))
                                 for s in (1, -1)) >= DEFECT_MIN_AREA_MM2:
            onset = k
    return {"peak": peak, "onset": onset, "peaks": peaks}


def score_run(report: dict, fault_truth: dict | None, *, truth_maps: dict,
              footprints: Footprints | None = None, reconstruction: dict | None = None,
              process_s: float | None = None, monitor_s: float | None = None,
              wall_s: float | None = None,
              expected_process_scale: float | None = None,
              track_truth: dict | None = None, truth_validity: dict | None = None,
              event_tolerance_mm: float = DEFECT_MIN_HEIGHT_MM) -> dict:
    """Score one run strictly (see the module's definitions).

    Parameters
    ----------
    report : report.json content
    fault_truth : faults.json content (``{"faults": [...]}``) or None (a control)
    truth_maps : layer -> :class:`dm2.bench.truth_maps.TruthMap`
    footprints : track id -> {layer: (xy_O, area)}; default: from the regions' boxes
    reconstruction : per layer ``{"rms_mm": ...}`` (measured against the true surface)
    process_s, monitor_s, wall_s : process seconds simulated, pipeline and total wall seconds
    expected_process_scale : the deposition scale against nominal that the twin's
        ``[twin_process]`` deposits at (its factors and its efficiency curve's loss on a flat
        coupon, dm2.cli.bench_runner), or None
    track_truth : track id -> its flagged vertices against the reference and the true surface
        (:func:`dm2.bench.reconstruction.truth_checks`), kept in each track's entry as
        ``truth``; ``false_tracks_part_deviates`` lists the false tracks where the part itself
        stands off the reference (the monitor's model, not its measurement, is off there)
    event_tolerance_mm : the run's event tolerance [mm] (``[monitor] delta_global_mm``): the
        height a fault's truth must reach to qualify and to explain a track
    truth_validity : the twin's check of its own truth (``truth/validity.json``), kept as
        ``truth_validity``; ``truth_valid`` is False when it failed (:func:`truth_invalid`:
        such a run's figures are not to be counted)
    """
    level = float(event_tolerance_mm)
    neutral_level = min(NEUTRAL_MIN_HEIGHT_MM, level)
    faults = list((fault_truth or {}).get("faults", []))
    foot = footprints_from_regions(report) if footprints is None else footprints
    tracks = {int(t["id"]): t for t in report.get("tracks", [])}
    pops = [_fault_population(f, truth_maps, len(faults), level) for f in faults]

    # which fault each track explains, in which layer and how well
    explains: dict[int, list[tuple[int, int, float]]] = {}  # fault idx -> (tid, layer, share)
    verdict: dict[int, dict] = {}
    for tid, t in sorted(tracks.items()):
        s = track_sign(t["kind"])
        layers = foot.get(tid, {})
        best, neutral_share = 0.0, 0.0
        for i, (f, pop) in enumerate(zip(faults, pops, strict=True)):
            if pop["onset"] is None:
                continue
            hits = []
            for k, (xy, w) in sorted(layers.items()):
                tm = truth_maps.get(k)
                if tm is None or k < pop["onset"]:
                    continue
                mask = _restrict(tm.mask(s, level, DILATION_MM),
                                 _support(f, tm, len(faults)))
                share = tm.fraction_in(mask, xy, w)
                best = max(best, share)
                if share >= EXPLAIN_FRACTION:
                    hits.append((k, share))
            if hits:
                explains.setdefault(i, []).append((tid, hits[0][0], max(h[1] for h in hits)))
        for k, (xy, w) in layers.items():
            tm = truth_maps.get(k)
            if tm is not None:
                neutral_share = max(neutral_share, tm.fraction_in(
                    tm.mask(s, neutral_level, DILATION_MM), xy, w))
        area = max((float(np.sum(w)) for _, w in layers.values()), default=0.0)
        verdict[tid] = {"id": tid, "kind": t["kind"], "area_mm2": area,
                        "best_share": best, "neutral_share": neutral_share, "verdict": None,
                        "faults": [], "truth": (track_truth or {}).get(tid)}

    scores = []
    for i, (f, pop) in enumerate(zip(faults, pops, strict=True)):
        ex = explains.get(i, [])
        # the earliest explaining track, then the largest, is the fault's true track
        ex.sort(key=lambda e: (e[1], -verdict[e[0]]["area_mm2"]))
        for n, (tid, _, _) in enumerate(ex):
            verdict[tid]["faults"].append(f.get("id", i))
            if n == 0:
                verdict[tid]["verdict"] = "true"
            elif verdict[tid]["verdict"] is None:
                verdict[tid]["verdict"] = "fragment"
        scores.append(_fault_score(f, pop, ex, report, foot, truth_maps, level))
    findings = _score_findings(report, faults, scores, expected_process_scale)
    for v in verdict.values():
        if v["verdict"] is None:
            drift = ((v["truth"] or {}).get("drift_share") or 0.0) >= DRIFT_SHARE
            v["verdict"] = ("neutral" if faults and v["neutral_share"] >= EXPLAIN_FRACTION
                            else "drift" if drift else "false")
    by = {k: [v["id"] for v in verdict.values() if v["verdict"] == k]
          for k in ("true", "fragment", "neutral", "drift", "false")}
    alarms = realtime_false_alarms(report, truth_maps, neutral_level)
    rms = [v["rms_mm"] for v in (reconstruction or {}).values()]
    hours = process_s / 3600.0 if process_s else None
    expectations = report.get("expectations", [])
    return {"faults": scores, "tracks": list(verdict.values()), "event_tolerance_mm": level,
            "true_tracks": by["true"], "fragments": by["fragment"],
            "neutral_tracks": by["neutral"], "drift_tracks": by["drift"],
            "drift_area_mm2": float(sum(verdict[t]["area_mm2"] for t in by["drift"])),
            "false_tracks": by["false"],
            "false_tracks_part_deviates": [t for t in by["false"]
                                           if (verdict[t]["truth"] or {}).get("part_deviates")],
            "false_area_mm2": float(sum(verdict[t]["area_mm2"] for t in by["false"])),
            "findings": findings,
            "false_findings": sum(1 for f in findings if f["verdict"] == "false"),
            "control": not faults, "realtime_alarms": alarms["alarms"],
            "realtime_false_alarms": alarms["false"],
            "realtime_false_alarms_per_hour": alarms["false"] / hours if hours else None,
            "expectations": expectations,
            "expect_passed": all(e.get("passed") for e in expectations),
            "layers": len(report.get("layers", [])),
            "reconstruction_rms_mm": float(np.sqrt(np.mean(np.square(rms)))) if rms else None,
            "reconstruction_by_layer": {str(k): v for k, v in (reconstruction or {}).items()},
            "process_s": process_s, "monitor_s": monitor_s, "wall_s": wall_s,
            "realtime_factor": process_s / monitor_s if process_s and monitor_s else None,
            "realtime_factor_with_twin": process_s / wall_s if process_s and wall_s else None,
            "truth_validity": truth_validity, "truth_valid": not truth_invalid(truth_validity)}


def truth_invalid(truth_validity: dict | None) -> list[str]:
    """Why a run's truth is outside the twin's validity (its check's reasons; empty when it is
    valid or was not checked). The bench never scores such a run."""
    if not truth_validity or truth_validity.get("valid", True):
        return []
    return list(truth_validity.get("reasons") or ["outside validity"])


def _score_findings(report, faults, scores, expected_scale) -> list[dict]:
    """Each process finding's verdict (see the definitions); a finding that detects a fault
    before any track does (or where none does) marks the fault's score ``detected`` from the
    finding's first layer (``detected_by`` "process finding", the onset delay from there)."""
    out = []
    for fd in ((report.get("process") or {}).get("finding_details") or []):
        since, sign = int(fd["since_layer"]), int(fd["sign"])
        verdict = None
        for f, sc in zip(faults, scores, strict=True):
            if f["kind"] in LOCAL_FAULTS or sc["onset_layer"] is None:
                continue
            window = f.get("layers") or ()
            starts = (sc["onset_layer"], *([int(window[0])] if len(window) else []))
            if int(f.get("sign") or 1) == sign and any(abs(since - k) <= 1 for k in starts):
                verdict = "true"
                first = sc["first_layer_detected"]
                if not sc["detected"] or first is None or since < first:  # the earliest counts
                    sc.update(detected=True, detected_by="process finding", sign_ok=True,
                              detected_global=True, first_layer_detected=since,
                              onset_delay_layers=since - sc["onset_layer"], onset_delay_s=None)
        if verdict is None:
            ok = fd.get("kind", "offset") == "offset" and expected_scale is not None and \
                abs(float(fd["estimate"]) - expected_scale) <= FINDING_TOLERANCE
            verdict = "correct" if ok else "false"
        out.append({**fd, "verdict": verdict, "expected_scale": expected_scale})
    return out


def _fault_score(fault, pop, explained, report, foot, maps, level_mm) -> dict:
    """One fault's score; onset delay, IoU and height error at its true track's first
    explaining layer."""
    tracks = {int(t["id"]): t for t in report.get("tracks", [])}
    stamps = {int(ly["layer"]): ly.get("stamp_s") for ly in report.get("layers", [])}
    onset = pop["onset"]
    out = {"fault_id": fault.get("id"), "kind": fault["kind"], "sign": int(fault.get("sign") or 1),
           "peak_height_mm": pop["peak"], "qualifies": onset is not None, "onset_layer": onset,
           "detected": bool(explained), "track_ids": [e[0] for e in explained],
           "fragments": max(len(explained) - 1, 0),
           "detected_global": any(tracks[e[0]]["kind"] in GLOBAL_KINDS for e in explained),
           "sign_ok": bool(explained), "first_layer_detected": None,
           "onset_delay_layers": None, "onset_delay_s": None, "iou": None,
           "height_mm": None, "truth_height_mm": None, "height_error_mm": None}
    if not explained:
        return out
    tid, layer, _ = explained[0]
    out["first_layer_detected"] = layer
    out["onset_delay_layers"] = layer - onset
    if stamps.get(layer) is not None and stamps.get(onset) is not None:
        out["onset_delay_s"] = float(stamps[layer] - stamps[onset])
    tm = maps[layer]
    s = track_sign(tracks[tid]["kind"])
    xy, _ = foot[tid][layer]
    rows, cols, inside = tm.cells_of(xy)
    flagged = np.zeros(tm.deviation_mm.shape, bool)
    flagged[rows[inside], cols[inside]] = True
    truth = tm.mask(s, level_mm)
    union = np.count_nonzero(flagged | truth)
    out["iou"] = float(np.count_nonzero(flagged & truth) / union) if union else None
    out["truth_height_mm"] = truth_h = pop["peaks"].get(layer)
    devs = [abs(reg["max_deviation_mm"]) for ly in report.get("layers", [])
            if int(ly["layer"]) == layer for reg in ly.get("regions", [])
            if reg.get("track_id") == tid]
    if devs and truth_h is not None:
        out["height_mm"] = max(devs)
        out["height_error_mm"] = max(devs) - truth_h
    return out


def realtime_false_alarms(report: dict, maps: dict,
                          level_mm: float = NEUTRAL_MIN_HEIGHT_MM) -> dict:
    """How many real-time alarms the run raised and how many were false (see definitions):
    confirmed where the truth of the alarm's sign reaches ``level_mm`` at its centroid."""
    alarms = ((report.get("realtime") or {}).get("alarms")) or []
    closes = sorted((ly.get("stamp_s"), int(ly["layer"])) for ly in report.get("layers", [])
                    if ly.get("stamp_s") is not None)
    false = 0
    for a in alarms:
        layer = next((k for st, k in closes if st >= a["stamp_s"]),
                     closes[-1][1] if closes else None)
        s = track_sign(a["kind"])
        ok = False
        for k in (layer, None if layer is None else layer - 1):
            tm = maps.get(k) if k is not None else None
            if tm is not None and tm.fraction_in(
                    tm.mask(s, level_mm, DILATION_MM),
                    [a["centroid_xy_O_mm"]]) > 0:
                ok = True
        false += not ok
    return {"alarms": len(alarms), "false": false}
