"""Scoring a run's report against fault truth: detection, sign, onset, IoU, false positives,
F1; suite overrides; sweep expansion and the smallest reliably detected size."""

import math

import pytest

from dm2.bench import scoring
from dm2.bench.scoring import gaussian_radius_mm, iou_xy, score_run, summarize
from dm2.bench.suites import apply_overrides, parse_override, resolve_suite
from dm2.bench.sweep import summarize_sweep, sweep_cases


def _region(layer, tid, kind, box, area=20.0, dev=1.0):
    return {"layer": layer, "kind": kind, "area_mm2": area, "max_deviation_mm": dev,
            "bbox_min_O_mm": [box[0], box[1], 0.0], "bbox_max_O_mm": [box[2], box[3], 1.0],
            "track_id": tid}


def _report(regions_by_layer, tracks, n_layers=4):
    layers = [{"layer": k, "stamp_s": 5.0 * (k + 1),
               "regions": regions_by_layer.get(k, [])} for k in range(n_layers)]
    return {"layers": layers, "tracks": tracks,
            "expectations": [{"expect": "x", "passed": True}]}


def _track(tid, kind, first, last):
    return {"id": tid, "kind": kind, "first_layer": first, "last_layer": last, "history": []}


BUMP_TRUTH = {"faults": [{"id": 0, "kind": "bump", "sign": 1, "layers": [1, 2, 3],
                          "region_O": {"bbox": [56, 56, 64, 64], "centers": [[60.0, 60.0]]},
                          "deviation_by_layer_mm": {"0": 0.0, "1": 1.2, "2": 1.1, "3": 1.0}}]}
BUMP_CFG = [{"kind": "bump", "center_O_mm": [60.0, 60.0], "height_mm": 1.2, "width_mm": 4.0}]


def test_gaussian_radius_and_iou():
    sigma = 4.0 / (2 * math.sqrt(2 * math.log(2)))
    # a Gaussian falls to half its peak at half the FWHM
    assert gaussian_radius_mm(1.0, sigma, 0.5) == pytest.approx(2.0)
    assert gaussian_radius_mm(0.3, sigma, 0.5) == 0.0
    assert iou_xy([0, 0, 2, 2], [1, 0, 3, 2]) == pytest.approx(1 / 3)
    assert iou_xy([0, 0, 1, 1], [2, 2, 3, 3]) == 0.0


def test_bump_detected_one_layer_late_with_iou_and_height_error():
    r = 1.7 * 1.0  # region box about the truth disc at 0.4 mm
    regs = {k: [_region(k, 7, "overbuild", [60 - r, 60 - r, 60 + r, 60 + r], dev=1.1)]
            for k in (2, 3)}
    report = _report(regs, [_track(7, "overbuild", 2, 3)])
    s = score_run(report, BUMP_TRUTH, fault_configs=BUMP_CFG, delta_mm=0.4,
                  reconstruction={0: {"rms_mm": 0.1}, 1: {"rms_mm": 0.2}},
                  process_s=20.0, monitor_s=2.0)
    (f,) = s["faults"]
    assert f["qualifies"] and f["detected"] and f["sign_ok"]
    assert f["onset_layer"] == 1 and f["first_layer_detected"] == 2
    assert f["onset_delay_layers"] == 1 and f["onset_delay_s"] == pytest.approx(5.0)
    # truth box: radius where a 1.2 mm, 4 mm FWHM blob exceeds 0.4 mm
    rt = gaussian_radius_mm(1.2, 4.0 / 2.3548, 0.4)
    assert f["iou"] == pytest.approx((2 * r) ** 2 / (2 * rt) ** 2, rel=1e-3)
    assert f["height_error_mm"] == pytest.approx(1.1 - 1.0)
    assert s["false_positive_tracks"] == [] and s["expect_passed"]
    assert s["realtime_factor"] == pytest.approx(10.0)
    assert s["reconstruction_rms_mm"] == pytest.approx(math.sqrt((0.01 + 0.04) / 2))


def test_wrong_sign_is_a_miss_and_far_global_track_a_false_positive():
    regs = {2: [_region(2, 1, "underbuild", [58, 58, 62, 62]),
                _region(2, 2, "overbuild", [10, 10, 14, 14]),
                _region(2, 3, "local_overbuild", [20, 20, 22, 22])]}
    report = _report(regs, [_track(1, "underbuild", 2, 2), _track(2, "overbuild", 2, 2),
                            _track(3, "local_overbuild", 2, 2)])
    s = score_run(report, BUMP_TRUTH, fault_configs=BUMP_CFG)
    (f,) = s["faults"]
    assert not f["detected"] and not f["sign_ok"]
    assert sorted(s["false_positive_tracks"]) == [1, 2]  # global kinds explaining no fault
    assert s["unmatched_local_tracks"] == [3]  # local warnings are not false positives
    summ = summarize({"a": s}, {"f1_min": 0.95, "max_false_positive_tracks": 0})
    assert summ["true_positives"] == 0 and summ["false_negatives"] == 1
    assert summ["f1"] == 0.0 and not summ["passed"]


def test_small_fault_is_outside_the_f1_population():
    truth = {"faults": [{**BUMP_TRUTH["faults"][0],
                         "deviation_by_layer_mm": {"1": 0.3, "2": 0.3}}]}
    s = score_run(_report({}, []), truth, fault_configs=BUMP_CFG)
    assert s["faults"][0]["peak_height_mm"] < scoring.DEFECT_MIN_HEIGHT_MM
    assert not s["faults"][0]["qualifies"]
    summ = summarize({"a": s, "control": score_run(_report({}, []), None)},
                     {"f1_min": 0.95, "max_onset_delay_layers": 1})
    assert summ["qualifying_defects"] == 0 and summ["f1"] == 1.0 and summ["passed"]


def test_global_underbuild_scored_over_the_part_outline():
    truth = {"faults": [{"id": 0, "kind": "feed_drift", "sign": -1, "layers": [1, 2, 3],
                         "region_O": {"bbox": [50, 55, 70, 65]},
                         "deviation_by_layer_mm": {"1": -0.2, "2": -0.6, "3": -1.0}}]}
    regs = {k: [_region(k, 4, "underbuild", [52, 55, 70, 65], area=150.0, dev=-0.7)]
            for k in (2, 3)}
    s = score_run(_report(regs, [_track(4, "underbuild", 2, 3)]), truth)
    (f,) = s["faults"]
    assert f["qualifies"] and f["detected"] and f["onset_layer"] == 2
    assert f["onset_delay_layers"] == 0
    assert f["iou"] == pytest.approx(0.9)
    assert f["truth_area_mm2"] == pytest.approx(200.0)
    assert f["height_error_mm"] == pytest.approx(0.7 - 1.0)


def test_overrides_and_suites(tmp_path):
    assert parse_override("toolpath.max_layers=12") == (["toolpath", "max_layers"], 12)
    assert parse_override("part.generator=pad") == (["part", "generator"], "pad")
    data = {"faults": [{"kind": "bump", "height_mm": 1.0}], "toolpath": {}}
    out = apply_overrides(data, ["faults.0.height_mm=0.7", "toolpath.strategy='single'"])
    assert out["faults"][0]["height_mm"] == 0.7 and out["toolpath"]["strategy"] == "single"
    assert data["faults"][0]["height_mm"] == 1.0  # the input is untouched
    with pytest.raises(ValueError, match="SECTION.KEY=VALUE"):
        parse_override("novalue")
    with pytest.raises(FileNotFoundError, match="neither a known suite"):
        resolve_suite("no_such_suite", tmp_path)
    (tmp_path / "regression").mkdir()
    with pytest.raises(FileNotFoundError, match="no scenario files"):
        resolve_suite("regression", tmp_path)


def test_shipped_regression_suite_covers_every_fault_kind():
    from dm2.bench.suites import load_suite_scenario
    from dm2.core.config import FaultConfig
    from scenarios import scenario_dir

    spec, files = resolve_suite("regression", scenario_dir() / "suites")
    kinds = set()
    controls = 0
    for f in files:
        sc = load_suite_scenario(f)
        kinds |= {x.kind for x in sc.faults}
        controls += not sc.faults and sc.expect.no_tracks
    all_kinds = set(FaultConfig.model_fields["kind"].annotation.__args__)
    assert kinds == all_kinds and controls == 1
    assert spec.targets["f1_min"] >= 0.95


def test_sweep_cases_and_smallest_reliable_size():
    base = {"name": "b", "seed": 1, "faults": [{"kind": "bump", "height_mm": 1.0}]}
    cases = sweep_cases(base, [0.2, 0.6], [5, 6])
    assert [(c["size"], c["seed"]) for c in cases] == [(0.2, 5), (0.2, 6), (0.6, 5), (0.6, 6)]
    assert cases[1]["scenario"]["faults"][0]["height_mm"] == 0.2
    assert base["faults"][0]["height_mm"] == 1.0
    with pytest.raises(ValueError, match="no faults\\[1\\]"):
        sweep_cases(base, [0.2], [1], fault_index=1)
    res = [{"size": s, "seed": k, "detected": d, "sign_ok": d, "peak_height_mm": s}
           for s, k, d in [(0.2, 1, False), (0.2, 2, True), (0.4, 1, True), (0.4, 2, False),
                           (0.6, 1, True), (0.6, 2, True), (0.8, 1, True), (0.8, 2, True)]]
    summ = summarize_sweep(res)
    assert [r["probability"] for r in summ["by_size"]] == [0.5, 0.5, 1.0, 1.0]
    assert summ["smallest_reliable_size"] == 0.6
