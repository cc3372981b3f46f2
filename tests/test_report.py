"""Report folder: report.json, tracks.csv, PLY scalar fields, STL, PNGs, index.html, atomicity."""

import csv
import json
import shutil

import numpy as np
import pytest
import trimesh
from test_deviation import CELL, MON, gaussian, pad_heights, top_surface

from dm2.core.config import ExpectConfig, ExpectTrack
from dm2.defects.layer_analysis import LayerAnalysis
from dm2.reference.height_map import ReferenceMap
from dm2.report import REPORT_SCHEMA, ReportContent, check_output_dir, write_report
from dm2.report.meshes import read_ply_vertex_fields

CENTRE = (50.0, 70.0)


@pytest.fixture(scope="module")
def monitored():
    mon = LayerAnalysis(MON)
    for layer in range(6):
        ref_h, xx, yy = pad_heights(layer)
        meas = ref_h + (gaussian(xx, yy, CENTRE, 0.6 + 0.2 * layer, 5.0) if layer >= 2 else 0)
        mon.analyse_layer(top_surface(meas), ReferenceMap(ref_h, CELL, layer))
    mon.finish()
    return mon


def test_report_folder_contents(tmp_path, monitored):
    out = tmp_path / "run" / "report"
    truth = {"faults": [{"kind": "bump", "center_O_mm": list(CENTRE), "layers": [2, 5]},
                        {"kind": "dent", "center_O_mm": [90.0, 20.0], "layers": [1, 3]},
                        {"id": 2, "kind": "feed_step", "sign": 1, "layers": [2, 3, 4],
                         "region_O": {"bbox": [45.0, 66.0, 48.0, 75.0], "centers": []},
                         "deviation_by_layer_mm": {"0": 0.0, "1": 0.0, "2": 0.3, "3": 0.6,
                                                   "4": 0.9}},
                        {"id": 3, "kind": "clog", "sign": -1, "layers": [3],
                         "region_O": {"bbox": [45.0, 66.0, 48.0, 75.0], "centers": []}}]}
    expect = ExpectConfig(tracks=(ExpectTrack(kind="overbuild", near_mm=(52.0, 68.0)),))
    rep = write_report(out, monitored.results, monitored.tracker.tracks,
                       ReportContent(config_toml='name = "x"\n', dropped={"stale_pose": 3},
                                     timing={"monitor_s": 1.5}, fault_truth=truth,
                                     expect=expect))
    on_disk = json.loads((out / "report.json").read_text())
    assert on_disk == rep
    assert {"schema", "layers", "tracks", "dropped", "timing"} <= set(rep)
    assert rep["schema"] == REPORT_SCHEMA and rep["dropped"] == {"stale_pose": 3}
    (track,) = rep["tracks"]
    assert (track["id"], track["kind"], track["first_layer"], track["last_layer"]) == \
        (1, "overbuild", 2, 5)
    assert track["trend"] == "amplifying"
    heights = [track["height_mm"][str(k)] for k in range(2, 6)]
    assert np.allclose(heights, [1.0, 1.2, 1.4, 1.6], atol=0.05)
    assert all(track["area_mm2"][str(k)] > 10 for k in range(2, 6))
    assert [len(layer["regions"]) for layer in rep["layers"]] == [0, 0, 1, 1, 1, 1]
    assert rep["layers"][3]["regions"][0]["track_id"] == 1
    assert rep["fault_truth"][0]["detected"] and rep["fault_truth"][0]["track_id"] == 1
    assert not rep["fault_truth"][1]["detected"]
    assert rep["fault_truth"][2]["detected"] and rep["fault_truth"][2]["distance_mm"] == \
        pytest.approx(2.0, abs=0.3)
    assert rep["fault_truth"][2]["detection_delay_layers"] == 0
    # the truth reached 0.5 mm only at layer 3: found a layer before it (the bump's entry has
    # no per-layer truth, so no onset)
    assert rep["fault_truth"][2]["truth_onset_layer"] == 3
    assert rep["fault_truth"][2]["onset_delay_layers"] == -1
    assert rep["fault_truth"][0]["truth_onset_layer"] is None
    assert rep["fault_truth"][0]["onset_delay_layers"] is None
    assert not rep["fault_truth"][3]["detected"]  # wrong sign
    assert rep["expectations"] == [{"expect": "overbuild track near [52.0, 68.0]",
                                    "passed": True, "track_ids": [1]}]
    assert (out / "config.toml").read_text() == 'name = "x"\n'
    rows = list(csv.DictReader(open(out / "tracks.csv")))
    assert [int(r["layer"]) for r in rows] == [2, 3, 4, 5]
    assert rows[1]["state"] == "growing"
    # PLY scalar fields round-trip
    res = monitored.results[4]
    fields = read_ply_vertex_fields(out / "meshes" / "layer_004.ply")
    assert {"scalar_signed_distance", "scalar_class", "scalar_weight", "red"} <= set(fields)
    assert np.allclose(fields["scalar_signed_distance"], res.deviation.signed_distance_mm,
                       atol=1e-5)
    assert np.array_equal(fields["scalar_class"], res.deviation.class_code)
    ply = trimesh.load(out / "meshes" / "layer_004.ply", process=False)
    assert len(ply.faces) == len(res.deviation.faces)
    stl = trimesh.load(out / rep["files"]["reference"][0])
    assert stl.bounds[1][2] == pytest.approx(0.8 * 6, abs=1e-6)
    assert all(name.endswith(".svg") for name in rep["files"]["track_plots"])
    for name in rep["files"]["deviation_maps"]:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(rep["files"]["deviation_maps"]) == 6
    assert rep["files"]["figures"] == ["plots/overview.png", "plots/timeline.png"]
    # height = the largest deviation from the reference; the box's z extent has its own name
    assert track["peak_deviation_mm"] == pytest.approx(1.6, abs=0.05)
    assert all(h["height_mm"] == pytest.approx(abs(h["max_deviation_mm"]))
               for h in track["history"])
    assert all(h["box_extent_z_mm"] >= h["height_mm"] - 1e-9 for h in track["history"])
    assert float(rows[0]["height_mm"]) == pytest.approx(abs(float(rows[0]["max_deviation_mm"])),
                                                         abs=1e-4)
    html = (out / "index.html").read_text()
    assert "Overbuild at (50.0, 70.0) mm, from layer 2 to 5" in html
    assert "mm², +1.5" in html and "growing 0.20 mm/layer (track 1)" in html
    assert "truth ≥ 0.5 mm from" in html and "delay after truth ≥ 0.5 mm [layers]" in html
    for name in rep["files"]["track_plots"] + rep["files"]["meshes"] + ["report.json"]:
        assert f'"{name}"' in html
    assert [p.name for p in out.parent.iterdir()] == ["report"]  # no temp folders left


def test_rewrite_replaces_its_own_files_keeps_a_users_and_failure_leaves_nothing(tmp_path,
                                                                                   monitored):
    out = tmp_path / "rep"
    first = write_report(out, monitored.results, monitored.tracker.tracks)
    write_report(out, monitored.results[:2], [], ReportContent(map_layers=[1]))  # earlier run
    assert json.loads((out / "report.json").read_text())["tracks"] == []
    for name in set(first["files"]["meshes"]) - {f"meshes/layer_{r.layer:03d}.ply"
                                                 for r in monitored.results[:2]}:
        assert not (out / name).exists()  # the earlier report's files are gone
    (out / "thesis.tex").write_text("mine")
    with pytest.raises(ValueError, match="thesis.tex.*--force"):
        write_report(out, monitored.results[:2], [], ReportContent(map_layers=[1]))
    write_report(out, monitored.results[:1], [],
                 ReportContent(map_layers=[monitored.results[0].layer]), force=True)
    assert (out / "thesis.tex").read_text() == "mine"
    assert json.loads((out / "report.json").read_text())["meta"] is not None
    assert len(list((out / "meshes").glob("layer_*.ply"))) == 1
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "report.json").write_text("a user's file")
    with pytest.raises(ValueError, match="did not write"):
        write_report(mine, monitored.results, [], force=True)
    assert (mine / "report.json").read_text() == "a user's file"
    shutil.rmtree(mine)
    with pytest.raises(ValueError, match="map layer 9"):
        write_report(tmp_path / "bad", monitored.results, [], ReportContent(map_layers=[9]))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rep"]


def test_unwritable_output_is_refused_before_work(tmp_path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    with pytest.raises(ValueError, match="file.txt"):
        check_output_dir(blocker / "report")
    with pytest.raises(ValueError, match="not a folder"):
        check_output_dir(blocker)


def test_expectations_no_tracks_global_and_local(monitored):
    from dm2.defects.track import Track
    from dm2.report.report_json import check_expectations

    local = Track(id=7, kind="local_underbuild", first_layer=1, last_layer=1)
    res = check_expectations([local], ExpectConfig(no_tracks=True))
    assert res == [{"expect": "no overbuild/underbuild tracks", "passed": True, "track_ids": []}]
    res = check_expectations([local] + monitored.tracker.tracks,
                             ExpectConfig(no_tracks=True, no_local_tracks=True))
    assert [(r["passed"], r["track_ids"]) for r in res] == [(False, [1]), (False, [7])]


def test_expected_global_track_met_by_a_process_finding_of_its_sign():
    """A process finding reports a global over- or underbuild of the whole part: it meets an
    expected global track of its sign and no other expectation (local kinds, absent tracks)."""
    from dm2.defects.track import Track
    from dm2.report.report_json import check_expectations

    over = {"kind": "offset", "quantity": "deposition scale", "estimate": 1.10, "sign": 1,
            "since_layer": 0, "text": "deposition efficiency 10 % above nominal since layer 0"}
    expect = ExpectConfig(
        tracks=(ExpectTrack(kind="overbuild", near_mm=(60.0, 60.0), within_mm=15.0,
                            from_layer=4),
                ExpectTrack(kind="underbuild"), ExpectTrack(kind="local_overbuild")),
        absent=(ExpectTrack(kind="underbuild"),))
    under = Track(id=3, kind="underbuild", first_layer=2, last_layer=5)
    res = check_expectations([under], expect, [over])
    assert res == [
        {"expect": "overbuild track near [60.0, 60.0]", "passed": True, "track_ids": [],
         "findings": [over["text"]]},
        {"expect": "underbuild track", "passed": True, "track_ids": [3]},
        {"expect": "local_overbuild track", "passed": False, "track_ids": []},
        {"expect": "no underbuild track", "passed": False, "track_ids": [3]}]
    # without the finding, or with one of the other sign, the overbuild is missed
    for findings in ((), ({**over, "sign": -1},)):
        assert check_expectations([under], expect, findings)[0]["passed"] is False
    # the inspection sheet names what met it
    from dm2.report.html import _truth
    sheet = _truth({"expectations": res})
    assert ("<td class='l'>overbuild track near [60.0, 60.0]</td><td>met</td><td class='l'>"
            f"process finding: {over['text']}</td>") in sheet
    assert "<td class='l'>no underbuild track</td><td>MISSED</td><td class='l'>3</td>" in sheet
