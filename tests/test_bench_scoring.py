"""Strict scoring against truth maps (every track counts; explained, fragment, neutral, false;
real-time false alarms), monitors that flag everything or nothing; suite overrides; sweep
expansion and the smallest reliably detected size."""

import math

import numpy as np
import pytest

from dm2.bench import scoring
from dm2.bench.scoring import score_run
from dm2.bench.suite_score import summarize
from dm2.bench.suites import apply_overrides, parse_override, resolve_suite
from dm2.bench.sweep import summarize_sweep, sweep_cases
from dm2.bench.truth_maps import TruthMap, load_truth_maps

CELL = 0.25
N = 160  # 40 x 40 mm map, cell (0, 0) centred at (0.125, 0.125)
XC = (np.arange(N) + 0.5) * CELL
GX, GY = np.meshgrid(XC, XC)
PART = (np.abs(GX - 20.0) <= 10.0) & (np.abs(GY - 20.0) <= 10.0)  # a 20 x 20 mm part
LAYERS = range(4)


def blob(cx, cy, peak, fwhm=4.0):
    s = fwhm / (2 * math.sqrt(2 * math.log(2)))
    return peak * np.exp(-((GX - cx) ** 2 + (GY - cy) ** 2) / (2 * s * s))


def maps(dev_by_layer):
    return {k: TruthMap(k, np.asarray(d, float), CELL, 0.5 * CELL, 0.5 * CELL)
            for k, d in dev_by_layer.items()}


def report(tracks, stamps_s=10.0, alarms=()):
    """``tracks``: {id: (kind, {layer: mask})}; a report with one region per track and layer."""
    layers = []
    for k in LAYERS:
        regs = []
        for tid, (kind, by_layer) in tracks.items():
            m = by_layer.get(k)
            if m is None or not m.any():
                continue
            regs.append({"track_id": tid, "kind": kind, "area_mm2": m.sum() * CELL ** 2,
                         "max_deviation_mm": 1.0 if "over" in kind else -1.0,
                         "bbox_min_O_mm": [GX[m].min(), GY[m].min(), 0.0],
                         "bbox_max_O_mm": [GX[m].max(), GY[m].max(), 1.0]})
        layers.append({"layer": k, "stamp_s": stamps_s * (k + 1), "regions": regs})
    return {"layers": layers, "expectations": [],
            "tracks": [{"id": t, "kind": kind} for t, (kind, _) in tracks.items()],
            "realtime": {"alarms": list(alarms)}}


def footprints(tracks):
    return {tid: {k: (np.column_stack([GX[m], GY[m]]), np.full(m.sum(), CELL ** 2))
                  for k, m in by_layer.items() if m.any()}
            for tid, (_, by_layer) in tracks.items()}


def truth(kind, sign, centers=None):
    region = {"bbox": [10, 10, 30, 30], **({"centers": centers} if centers else {})}
    return {"faults": [{"id": 0, "kind": kind, "sign": sign, "region_O": region}]}


def run(tracks, dev_by_layer, fault_truth, alarms=(), process_s=40.0):
    return score_run(report(tracks, alarms=alarms), fault_truth, truth_maps=maps(dev_by_layer),
                     footprints=footprints(tracks), process_s=process_s)


BUMP_DEV = {k: (blob(25.0, 14.0, 1.2) if k >= 1 else np.zeros((N, N))) for k in LAYERS}


def test_track_on_the_bump_explains_it_second_is_fragment_others_false_or_neutral():
    on_bump = blob(25.0, 14.0, 1.2) >= 0.6
    small = (np.abs(GX - 25.0) <= 0.6) & (np.abs(GY - 14.0) <= 0.6)
    shallow = (np.abs(GX - 12.0) <= 2.0) & (np.abs(GY - 12.0) <= 2.0)
    dev = {k: v + np.where(shallow, 0.35, 0.0) * (k >= 1) for k, v in BUMP_DEV.items()}
    far = (np.abs(GX - 12.0) <= 1.5) & (np.abs(GY - 25.0) <= 1.5)
    tracks = {1: ("local_overbuild", {2: on_bump, 3: on_bump}),
              2: ("overbuild", {3: small}),
              3: ("underbuild", {2: on_bump}),  # right place, wrong sign
              4: ("local_overbuild", {2: shallow}),  # on 0.35 mm of true deviation
              5: ("local_overbuild", {1: far})}
    alarms = [{"stamp_s": 15.0, "kind": "overbuild", "centroid_xy_O_mm": [25.0, 14.5]},
              {"stamp_s": 15.0, "kind": "overbuild", "centroid_xy_O_mm": [12.0, 25.0]},
              {"stamp_s": 35.0, "kind": "underbuild", "centroid_xy_O_mm": [25.0, 14.0]}]
    s = run(tracks, dev, truth("bump", 1, [[25.0, 14.0]]), alarms)
    (f,) = s["faults"]
    assert f["qualifies"] and f["onset_layer"] == 1 and f["peak_height_mm"] == pytest.approx(
        1.2, abs=0.01)
    assert f["detected"] and f["track_ids"] == [1, 2] and f["fragments"] == 1
    assert f["first_layer_detected"] == 2 and f["onset_delay_layers"] == 1
    assert s["true_tracks"] == [1] and s["fragments"] == [2]
    assert s["neutral_tracks"] == [4] and sorted(s["false_tracks"]) == [3, 5]
    assert s["false_area_mm2"] == pytest.approx((on_bump.sum() + far.sum()) * CELL ** 2)
    assert s["realtime_alarms"] == 3 and s["realtime_false_alarms"] == 2
    assert s["realtime_false_alarms_per_hour"] == pytest.approx(2 / (40.0 / 3600.0))
    summ = summarize({"bump": s})
    assert summ["precision"] == pytest.approx(1 / 3) and summ["recall"] == 1.0
    assert summ["f1"] == pytest.approx(0.5) and summ["gate_passed"]


def test_track_before_onset_or_mostly_outside_explains_nothing():
    half_out = (np.abs(GX - 25.0) <= 6.0) & (np.abs(GY - 14.0) <= 6.0)  # 12 x 12 mm box
    tracks = {1: ("overbuild", {0: blob(25.0, 14.0, 1.0) >= 0.6}),  # layer 0: no fault yet
              2: ("overbuild", {2: half_out})}
    s = run(tracks, BUMP_DEV, truth("bump", 1, [[25.0, 14.0]]))
    assert not s["faults"][0]["detected"] and s["false_tracks"] == [1, 2]


def test_false_tracks_where_the_part_itself_deviates_are_listed_and_still_false():
    """On a control, two tracks: one whose flagged vertices lie on the twin's true surface (the
    part stands off the reference: listed) and one the measurement put off the truth (not
    listed); both count as false, and the suite total counts the first."""
    spot = (np.abs(GX - 25.0) <= 1.5) & (np.abs(GY - 14.0) <= 1.5)
    other = (np.abs(GX - 12.0) <= 1.5) & (np.abs(GY - 25.0) <= 1.5)
    tracks = {1: ("overbuild", {2: spot}), 2: ("underbuild", {3: other})}
    zero = {k: np.zeros((N, N)) for k in LAYERS}
    vs_truth = {1: {"n_vertices": 36, "deviation_median_mm": 0.9,
                    "truth_distance_median_mm": 0.05, "truth_distance_p90_mm": 0.1,
                    "part_deviates": True},
                2: {"n_vertices": 36, "deviation_median_mm": -0.6,
                    "truth_distance_median_mm": 0.55, "truth_distance_p90_mm": 0.7,
                    "part_deviates": False}}
    s = score_run(report(tracks), None, truth_maps=maps(zero), footprints=footprints(tracks),
                  track_truth=vs_truth)
    assert s["control"] and sorted(s["false_tracks"]) == [1, 2]
    assert s["false_tracks_part_deviates"] == [1]
    assert [t["truth"] for t in sorted(s["tracks"], key=lambda t: t["id"])] == \
        [vs_truth[1], vs_truth[2]]
    summ = summarize({"control": s})
    assert summ["false_tracks"] == 2 and summ["false_tracks_part_deviates"] == 1
    assert not summ["gate_passed"]
    without = score_run(report(tracks), None, truth_maps=maps(zero),
                        footprints=footprints(tracks))
    assert without["false_tracks_part_deviates"] == [] and \
        all(t["truth"] is None for t in without["tracks"])


def test_a_fault_below_half_a_millimetre_is_no_defect_and_tracks_on_it_are_neutral():
    dev = {k: blob(25.0, 14.0, 0.4) for k in LAYERS}
    tracks = {1: ("local_overbuild", {2: blob(25.0, 14.0, 0.4) >= 0.25})}
    s = run(tracks, dev, truth("bump", 1, [[25.0, 14.0]]))
    assert not s["faults"][0]["qualifies"] and s["neutral_tracks"] == [1]
    assert summarize({"a": s})["f1"] == 1.0  # nothing to find, nothing false


def _suite(monitor):
    """Four faulty runs and a control, each scored with the tracks ``monitor(dev)`` reports."""
    zero = np.zeros((N, N))
    cases = {
        "bump": (BUMP_DEV, truth("bump", 1, [[25.0, 14.0]])),
        "dent": ({k: (-blob(13.0, 27.0, 1.0) if k >= 2 else zero) for k in LAYERS},
                 truth("dent", -1, [[13.0, 27.0]])),
        "corner": ({k: blob(29.0, 29.0, 0.3 * k, 6.0) for k in LAYERS},
                   truth("corner_dwell", 1, [[29.0, 29.0]])),
        "feed_step": ({k: np.where(PART, 0.3 * k, 0.0) for k in LAYERS},
                      truth("feed_step", 1)),
        "control": ({k: zero for k in LAYERS}, None)}
    return {name: run(monitor(dev), dev, t) for name, (dev, t) in cases.items()}


def test_a_monitor_flagging_the_whole_part_every_layer_scores_f1_below_half():
    runs = _suite(lambda dev: {1: ("overbuild", {k: PART for k in LAYERS})})
    s = summarize(runs)
    assert s["qualifying_faults"] == 4
    assert runs["feed_step"]["faults"][0]["detected"]  # the whole part did overbuild there
    assert not runs["bump"]["faults"][0]["detected"]  # a bump is not the whole part
    assert s["f1"] < 0.5
    assert s["false_tracks_per_control"] == {"control": 1} and not s["gate_passed"]


def test_a_monitor_reporting_nothing_has_recall_zero():
    s = summarize(_suite(lambda dev: {}))
    assert s["qualifying_faults"] == 4 and s["recall"] == 0.0 and s["f1"] == 0.0
    assert s["false_tracks"] == 0 and s["gate_passed"]


def test_suite_targets_and_gate():
    runs = _suite(lambda dev: {})
    s = summarize(runs, {"f1_min": 0.95, "max_false_tracks": 0, "max_false_alarms_per_hour": 0})
    assert s["target_checks"] == {"f1": False, "false_tracks": True, "false_alarms": True}
    assert not s["passed"]


def test_truth_maps_round_trip(tmp_path):
    from twin.world.truth import write_deviation_maps

    faulty = {0: np.zeros((80, 80)), 1: np.zeros((80, 80))}
    nominal = {0: np.zeros((80, 80)), 1: np.zeros((80, 80))}
    nominal[1][30:40, 30:50] = 0.8
    faulty[1][30:40, 30:50] = 0.8
    faulty[1][34:36, 40:42] += 0.6  # a 0.5 x 0.5 mm bump at x 10.0-10.5, y 8.5-9.0
    write_deviation_maps(tmp_path, faulty, nominal, 0.25, margin_mm=1.0)
    m = load_truth_maps(tmp_path)
    assert sorted(m) == [0, 1]
    assert m[1].deviation_mm.shape == (10 + 8, 20 + 8)  # built window plus 1 mm margin
    assert m[1].area_mm2(m[1].mask(1, 0.5)) == pytest.approx(0.25)
    rows, cols, inside = m[1].cells_of([[10.2, 8.7], [0.1, 0.1]])
    assert m[1].deviation_mm[rows[0], cols[0]] == pytest.approx(0.6) and list(inside) == [
        True, False]
    assert not m[0].mask(1, 0.2).any()
    assert scoring.DILATION_MM == 1.0


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


def test_shipped_regression_suite_is_realistic():
    from dm2.bench.suites import load_suite_scenario
    from dm2.core.config import MonitorConfig, ToolpathConfig, read_toml
    from scenarios import scenario_dir
    from twin.schema import FaultConfig

    spec, files = resolve_suite("regression", scenario_dir() / "suites")
    assert len(files) >= 12
    kinds, parts, seeds_by_fault = set(), set(), {}
    controls = 0
    for f in files:
        assert "monitor" not in read_toml(f), f"{f.name}: no per-scenario [monitor] section"
        sc = load_suite_scenario(f)
        assert sc.monitor == MonitorConfig() and sc.toolpath == ToolpathConfig()  # defaults
        assert sc.toolpath.strategy == "double" and sc.toolpath.contour_angle_deg > 0
        kinds |= {x.kind for x in sc.faults}
        parts.add(sc.part.generator or sc.part.stl.rsplit("/", 1)[-1])
        if not sc.faults:
            controls += 1
            assert sc.expect.no_tracks and sc.expect.no_local_tracks
        for x in sc.faults:
            if x.center_O_mm is not None:  # blobs off the part's centre (60, 60)
                assert math.dist(x.center_O_mm, (60.0, 60.0)) > 5.0, f.name
        key = tuple((x.kind, x.center_O_mm) for x in sc.faults)
        seeds_by_fault.setdefault((sc.part.model_dump_json(), key), set()).add(sc.seed)
    all_kinds = set(FaultConfig.model_fields["kind"].annotation.__args__)
    assert kinds == all_kinds and controls >= 3
    assert {"seven_sided", "box", "twisted_tower", "plate_with_hole.stl",
            "bracket_thin_wall.stl"} <= parts
    assert max(len(v) for v in seeds_by_fault.values()) >= 2  # some scenarios on two seeds
    assert spec.targets["f1_min"] >= 0.95 and spec.targets["max_false_tracks"] == 0


def test_paper_suite_says_what_must_and_must_not_appear():
    from dm2.bench.suites import load_suite_scenario
    from scenarios import scenario_dir

    _, files = resolve_suite("paper", scenario_dir() / "suites")
    assert len(files) == 4
    for f in files:
        sc = load_suite_scenario(f)
        assert sc.expect.tracks and sc.expect.absent, f.name


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


def _with_findings(rep, *findings):
    rep["process"] = {"finding_details": [
        {"kind": k, "quantity": "deposition scale", "estimate": e, "sign": s, "since_layer": L,
         "text": ""} for k, e, s, L in findings]}
    return rep


FEED_STEP_DEV = {k: np.where(PART, 0.3 * k, 0.0) for k in LAYERS}  # onset: layer 2 (0.6 mm)


def test_process_findings_detect_global_faults_or_are_judged_against_the_twin_scale():
    # a change of the fault's sign from the fault's onset detects it (no track needed)
    rep = _with_findings(report({}), ("change", 1.3, 1, 2), ("change", 0.8, -1, 2),
                         ("change", 1.3, 1, 0))
    s = score_run(rep, truth("feed_step", 1), truth_maps=maps(FEED_STEP_DEV),
                  expected_process_scale=0.95)
    (f,) = s["faults"]
    assert f["onset_layer"] == 2 and f["detected"] and f["detected_by"] == "process finding"
    assert f["onset_delay_layers"] == 0
    assert [x["verdict"] for x in s["findings"]] == ["true", "false", "false"]  # sign, onset
    assert s["false_findings"] == 2 and s["false_tracks"] == []
    # a local fault is never explained by a process finding
    rep = _with_findings(report({}), ("change", 1.3, 1, 1))
    s = score_run(rep, truth("bump", 1, [[25.0, 14.0]]), truth_maps=maps(BUMP_DEV),
                  expected_process_scale=0.95)
    assert not s["faults"][0]["detected"] and s["findings"][0]["verdict"] == "false"


def test_a_finding_at_the_layer_the_fault_began_detects_it_before_its_truth_onset():
    """A feed step acting from layer 0 whose effect reaches 0.5 mm at layer 2 (FEED_STEP_DEV):
    a finding of its sign since layer 0 detects it, one of the other sign or since a layer
    before the fault began does not."""
    fault = truth("feed_step", 1)
    fault["faults"][0]["layers"] = [0, 1, 2, 3]
    rep = _with_findings(report({}), ("offset", 1.3, 1, 0), ("offset", 0.8, -1, 0))
    s = score_run(rep, fault, truth_maps=maps(FEED_STEP_DEV), expected_process_scale=0.95)
    (f,) = s["faults"]
    assert f["onset_layer"] == 2 and f["detected"] and f["detected_by"] == "process finding"
    assert f["first_layer_detected"] == 0 and f["onset_delay_layers"] == -2
    assert [x["verdict"] for x in s["findings"]] == ["true", "false"]
    fault["faults"][0]["layers"] = [3, 4]  # began at layer 3: a finding since 0 is not it
    s = score_run(_with_findings(report({}), ("offset", 1.3, 1, 0)), fault,
                  truth_maps=maps(FEED_STEP_DEV), expected_process_scale=0.95)
    assert s["findings"][0]["verdict"] == "false" and not s["faults"][0]["detected"]


def test_an_offset_on_a_control_is_correct_within_the_tolerance_of_the_twin_scale():
    zero = {k: np.zeros((N, N)) for k in LAYERS}
    tol = scoring.FINDING_TOLERANCE
    rep = _with_findings(report({}), ("offset", 0.95 + 0.99 * tol, -1, 0),
                         ("offset", 0.95 - 1.01 * tol, -1, 0), ("change", 0.95, -1, 1))
    s = score_run(rep, None, truth_maps=maps(zero), expected_process_scale=0.95)
    assert [x["verdict"] for x in s["findings"]] == ["correct", "false", "false"]
    assert s["false_findings"] == 2
    s = score_run(_with_findings(report({}), ("offset", 0.95, -1, 0)), None,
                  truth_maps=maps(zero), expected_process_scale=None)
    assert s["findings"][0]["verdict"] == "false"  # nothing to judge it against
    assert summarize({"c": s})["false_tracks_per_control"] == {"c": 1}  # counted as false


def test_the_twin_scale_is_the_factors_times_what_the_curve_takes_on_a_flat_coupon():
    """The twin's scale is the factors' ratio (feed x efficiency over the dense fraction) where
    its efficiency curve is flat near normal incidence (the default curve, flat to 30 deg); a
    curve that falls linearly from normal incidence takes more, as the jet's divergence and the
    deposit's ripples meet a flat coupon a few degrees off normal; a wide plume's coupon grows
    to keep a plateau."""
    from dm2.core.config import load_scenario
    from scenarios import resolve_scenario
    from twin.world.coupon import coupon_scale

    sc = load_scenario(resolve_scenario("pad"))
    twin = {"efficiency_factor": 1.15, "porosity": 0.04, "feed_g_min": sc.process.feed_g_min * 0.9}
    sc = sc.model_copy(update={"twin_process": sc.twin_process.model_copy(update=twin)})
    factors = 0.9 * 1.15 / 0.96  # feed x efficiency over the dense fraction
    assert sc.twin_process.efficiency_curve == "plateau"
    assert coupon_scale(sc) == pytest.approx(factors, rel=1e-12)

    def with_curve(curve, **more):
        return sc.model_copy(update={"twin_process": sc.twin_process.model_copy(
            update={"efficiency_curve": curve, **more})})

    linear = coupon_scale(with_curve("linear"))
    assert 0.85 * factors < linear < 0.995 * factors  # pad: a thin raster, small ripples
    assert coupon_scale(with_curve("linear")) == linear  # seeded: the same coupons
    assert coupon_scale(with_curve("cos2")) == pytest.approx(factors, rel=0.005)
    wide = coupon_scale(with_curve("linear", plume_sigma_factor=4.0))  # sigma 12 mm
    assert 0.85 * factors < wide < 0.995 * factors


def test_a_finding_before_the_track_sets_the_detection_onset():
    """A feed step from layer 2 (FEED_STEP_DEV) tracked only from layer 3 but reported as a
    process finding since layer 2 is detected at layer 2; a finding after the track changes
    nothing."""
    tracks = {1: ("overbuild", {3: PART})}
    base = score_run(report(tracks), truth("feed_step", 1), truth_maps=maps(FEED_STEP_DEV),
                     footprints=footprints(tracks))
    (f,) = base["faults"]
    assert f["detected"] and f["first_layer_detected"] == 3 and f["onset_delay_layers"] == 1
    early = score_run(_with_findings(report(tracks), ("offset", 1.3, 1, 2)), truth("feed_step", 1),
                      truth_maps=maps(FEED_STEP_DEV), footprints=footprints(tracks))
    (f,) = early["faults"]
    assert f["first_layer_detected"] == 2 and f["onset_delay_layers"] == 0
    assert f["detected_by"] == "process finding" and f["track_ids"] == [1]
    assert early["findings"][0]["verdict"] == "true" and early["false_tracks"] == []
    late = score_run(_with_findings(report(tracks), ("change", 1.3, 1, 3)), truth("feed_step", 1),
                     truth_maps=maps(FEED_STEP_DEV), footprints=footprints(tracks))
    (f,) = late["faults"]
    assert f["first_layer_detected"] == 3 and f["onset_delay_layers"] == 1
    assert "detected_by" not in f or f["detected_by"] != "process finding"
