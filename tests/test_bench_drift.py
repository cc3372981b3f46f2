"""Drift told from detections and false tracks: the reference the run used against the twin's
true surface at a track's flagged vertices (dm2.bench.reconstruction.truth_checks), and the
strict score's third kind (dm2.bench.scoring: drift neither true nor false)."""

from types import SimpleNamespace

import numpy as np
import pytest
from test_bench_scoring import CELL, GX, GY, LAYERS, N, footprints, maps, report

from dm2.bench.reconstruction import truth_checks
from dm2.bench.scoring import score_run
from dm2.bench.suite_score import summarize
from dm2.cli.cmd_bench import score_line
from dm2.defects.classify import CLASS_NAMES
from dm2.reference.height_map import ReferenceMap
from twin.world.heightfield import HeightField
from twin.world.truth import write_layer_surface


def _block(top_mm: float) -> HeightField:
    """A 30 x 20 mm block of flat top ``top_mm`` on a 60 mm plate (the twin's grid)."""
    hf = HeightField(size_mm=(60.0, 60.0), cell_mm=0.25, thickness_mm=5.0)
    x, y = hf.centres_mm()
    block = (x[None, :] > 15) & (x[None, :] < 45) & (y[:, None] > 20) & (y[:, None] < 40)
    hf._h[:] = np.where(block, top_mm, 0.0)
    return hf


def _reference(top_mm: float, layer: int) -> ReferenceMap:
    xc = (np.arange(120) + 0.5) * 0.5
    block = (xc[None, :] > 15) & (xc[None, :] < 45) & (xc[:, None] > 20) & (xc[:, None] < 40)
    return ReferenceMap(np.where(block, top_mm, 0.0), 0.5, layer=layer)


def test_a_top_that_outgrows_the_reference_is_drift_with_its_rate(tmp_path):
    """The reference stays at 11.5 mm while the true top grows 12.0, 12.15, 12.3 mm over
    layers 10-12 (+0.5 mm, then 0.15 mm/layer over the plan): the track on the top is drift
    from layer 10 at 0.15 mm/layer; a track on the plate (truth = reference) and one of the
    wrong sign on the top are not drift."""
    rng = np.random.default_rng(11)
    top = np.column_stack([rng.uniform(20, 40, 60), rng.uniform(24, 36, 60)])
    plate = np.column_stack([rng.uniform(20, 40, 20), rng.uniform(16.5, 18.5, 20)])
    results = []
    for k, z in ((10, 12.0), (11, 12.15), (12, 12.3)):
        write_layer_surface(_block(z), tmp_path / f"layer_{k:03d}.ply")
        v = np.concatenate([np.column_stack([top, np.full(60, z)]),
                            np.column_stack([plate, np.full(20, 0.7)]),
                            np.column_stack([top[:10], np.full(10, z)])])
        signed = np.concatenate([np.full(60, z - 11.5), np.full(20, 0.7), np.full(10, -0.6)])
        dev = SimpleNamespace(vertices_O=v, signed_distance_mm=signed,
                              class_code=np.full(90, CLASS_NAMES.index("overbuild")),
                              vertex_areas=lambda n=90: np.full(n, 0.25))
        regions = [SimpleNamespace(vertex_ids=np.arange(60)),
                   SimpleNamespace(vertex_ids=np.arange(60, 80)),
                   SimpleNamespace(vertex_ids=np.arange(80, 90))]
        results.append(SimpleNamespace(layer=k, deviation=dev, regions=regions,
                                       track_ids=[1, 2, 3], reference=_reference(11.5, k)))
    _, out = truth_checks(results, tmp_path, tolerance_mm=0.4)
    assert out[1]["drift_share"] == pytest.approx(1.0)
    assert out[1]["drift_since_layer"] == 10
    assert out[1]["drift_rate_mm_per_layer"] == pytest.approx(0.15, abs=1e-6)
    assert out[1]["true_offset_median_by_layer_mm"]["12"] == pytest.approx(0.8, abs=1e-6)
    assert out[2]["drift_share"] == 0.0 and out[2]["drift_since_layer"] is None
    assert out[3]["drift_share"] == 0.0  # the truth stands above the reference, not below
    # without a tolerance, no drift figures (the earlier behaviour)
    _, plain = truth_checks(results, tmp_path)
    assert "drift_share" not in plain[1]


def _truth(share, since=None, rate=None):
    return {"n_vertices": 30, "deviation_median_mm": 0.9, "truth_distance_median_mm": 0.1,
            "truth_distance_p90_mm": 0.2, "part_deviates": True, "drift_share": share,
            "drift_since_layer": since, "drift_rate_mm_per_layer": rate}


def test_drift_is_neither_true_nor_false_and_the_score_line_says_it():
    """A control with a track the truth confirms as drift (60 % of its area), one it does not
    (30 %): one drift track, one false; a faulty run's true track stays a detection."""
    a = (np.abs(GX - 25.0) <= 2.0) & (np.abs(GY - 14.0) <= 2.0)
    b = (np.abs(GX - 12.0) <= 1.5) & (np.abs(GY - 25.0) <= 1.5)
    tracks = {1: ("overbuild", {2: a, 3: a}), 2: ("overbuild", {3: b})}
    zero = {k: np.zeros((N, N)) for k in LAYERS}
    s = score_run(report(tracks), None, truth_maps=maps(zero), footprints=footprints(tracks),
                  track_truth={1: _truth(0.6, 2, 0.15), 2: _truth(0.3)})
    assert s["drift_tracks"] == [1] and s["false_tracks"] == [2]
    assert s["drift_area_mm2"] == pytest.approx(a.sum() * CELL ** 2)
    summ = summarize({"control": s})
    assert summ["drift_tracks"] == 1 and summ["false_tracks"] == 1
    assert summ["drift_area_mm2"] == pytest.approx(a.sum() * CELL ** 2)
    assert summ["precision"] == 0.0 and summ["false_tracks_per_control"] == {"control": 1}
    line = score_line(summ)
    assert "detections 0/0" in line and "drift 1 track(s) (16 mm²)" in line
    assert "false tracks 1 (9 mm²" in line
    # the drift track alone: the control's gate passes
    only = score_run(report({1: tracks[1]}), None, truth_maps=maps(zero),
                     footprints=footprints({1: tracks[1]}), track_truth={1: _truth(0.6, 2)})
    assert summarize({"c": only})["gate_passed"] and only["false_tracks"] == []


def test_the_report_says_a_drift_track_is_drift_and_how_fast_it_grows():
    """report.json's track_truth: track 1 drifts 0.15 mm/layer from layer 62; track 2 explains
    an injected fault (an event, not drift) though its part stands off too; track 3 is no
    drift."""
    from dm2.report.html import _truth as truth_html
    from dm2.report.html import drift_sentences

    rep = {"tracks": [{"id": 1, "kind": "overbuild"}, {"id": 2, "kind": "overbuild"},
                      {"id": 3, "kind": "underbuild"}],
           "fault_truth": [{"fault": {"kind": "bump", "layers": [3, 4]}, "detected": True,
                            "track_id": 2}],
           "track_truth": {"1": {**_truth(1.0, 62, 0.15), "drift_tolerance_mm": 0.4,
                                 "true_offset_median_by_layer_mm": {"62": 0.5, "70": 1.7}},
                           "2": {**_truth(0.9, 3, 0.3), "drift_tolerance_mm": 0.4},
                           "3": _truth(0.1)}}
    assert drift_sentences(rep) == [
        "Track 1 (overbuild) is drift: the part runs 0.15 mm/layer over the plan since layer "
        "62 (+1.70 mm in layer 70, beyond 0.4 mm under 100 % of the track)"]
    html = truth_html(rep)
    assert html.index("Injected faults") < html.index("Drift (the twin's truth)")
