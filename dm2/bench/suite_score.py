"""A suite's totals over its strictly scored runs (:func:`dm2.bench.scoring.score_run`), checked
against the suite's targets (:mod:`dm2.bench.suites`)."""

from __future__ import annotations

from dm2.bench.scoring import DEFECT_MIN_AREA_MM2, DEFECT_MIN_HEIGHT_MM


def summarize(runs: dict[str, dict], targets: dict | None = None) -> dict:
    """Suite totals of :func:`score_run` results (``runs``: scenario name -> result).

    ``targets`` may hold ``f1_min``, ``max_onset_delay_layers``, ``max_false_tracks`` and
    ``max_false_alarms_per_hour`` (each checked when present). ``gate_passed`` is False when a
    control has any false track (drift, confirmed by the truth, is not false).
    """
    tolerances = sorted({r.get("event_tolerance_mm", DEFECT_MIN_HEIGHT_MM) for r in runs.values()})
    qual = [f for r in runs.values() for f in r["faults"] if f["qualifies"]]
    detected = sum(1 for f in qual if f["detected"])
    true_t = sum(len(r["true_tracks"]) for r in runs.values())
    false_t = sum(len(r["false_tracks"]) + r.get("false_findings", 0) for r in runs.values())
    precision = true_t / (true_t + false_t) if true_t + false_t else 1.0
    recall = detected / len(qual) if qual else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    delays = [f["onset_delay_layers"] for f in qual if f["onset_delay_layers"] is not None]
    hours = sum(r["process_s"] or 0.0 for r in runs.values()) / 3600.0
    rt_false = sum(r["realtime_false_alarms"] for r in runs.values())
    controls = {name: len(r["false_tracks"]) + r.get("false_findings", 0)
                for name, r in runs.items() if r["control"]}
    out = {"qualifying_faults": len(qual), "detected_faults": detected,
           "missed_faults": len(qual) - detected, "true_tracks": true_t, "false_tracks": false_t,
           "false_findings": sum(r.get("false_findings", 0) for r in runs.values()),
           # false tracks where the twin's true part stands off the reference as measured
           "false_tracks_part_deviates": sum(len(r["false_tracks_part_deviates"])
                                             for r in runs.values()),
           "fragments": sum(len(r["fragments"]) for r in runs.values()),
           "neutral_tracks": sum(len(r["neutral_tracks"]) for r in runs.values()),
           # tracks no fault explains where the true part stands off the reference the run used
           "drift_tracks": sum(len(r.get("drift_tracks", [])) for r in runs.values()),
           "drift_area_mm2": float(sum(r.get("drift_area_mm2", 0.0) for r in runs.values())),
           "false_area_mm2": float(sum(r["false_area_mm2"] for r in runs.values())),
           "precision": precision, "recall": recall, "f1": f1,
           "max_onset_delay_layers": max(delays) if delays else None,
           "realtime_alarms": sum(r["realtime_alarms"] for r in runs.values()),
           "realtime_false_alarms": rt_false,
           "realtime_false_alarms_per_hour": rt_false / hours if hours > 0 else None,
           "process_h": hours, "false_tracks_per_control": controls,
           "gate_passed": all(n == 0 for n in controls.values()),
           "expectations_passed": all(r["expect_passed"] for r in runs.values()),
           "event_tolerance_mm": tolerances,
           "definition": "strict: every track counts; faults >= the run's event tolerance ("
                         + "/".join(f"{t:g}" for t in tolerances) + " mm) over "
                         f">= {DEFECT_MIN_AREA_MM2} mm2 (see dm2.bench.scoring)"}
    targets = dict(targets or {})
    checks = {}
    if "f1_min" in targets:
        checks["f1"] = f1 >= targets["f1_min"]
    if "max_onset_delay_layers" in targets:
        checks["onset"] = len(delays) == detected and all(
            d <= targets["max_onset_delay_layers"] for d in delays)
    if "max_false_tracks" in targets:
        checks["false_tracks"] = false_t <= targets["max_false_tracks"]
    if "max_false_alarms_per_hour" in targets:
        per_h = out["realtime_false_alarms_per_hour"] or 0.0
        checks["false_alarms"] = per_h <= targets["max_false_alarms_per_hour"]
    out["targets"] = targets
    out["target_checks"] = checks
    out["passed"] = out["expectations_passed"] and all(checks.values()) and out["gate_passed"]
    return out

