"""Report cost bounded by construction, on a synthetic run with many tracks: plots for the 20
most severe only, at most 12 maps, every track in the table, the verdict naming the five most
severe defects in order."""

from __future__ import annotations

import json
import re

from dm2.report import ReportContent, write_report
from dm2.report.contents import MAP_LAYERS, PLOTTED_TRACKS
from dm2.report.summary import by_severity, is_defect, severity
from dm2.report.synthetic import synthetic_run


def test_many_tracks_get_bounded_figures_and_a_ranked_verdict(tmp_path):
    results, tracks, realtime = synthetic_run(n_layers=14, n_tracks=80, size_mm=40.0)
    assert len(tracks) >= 80
    stages = []
    rep = write_report(tmp_path / "r", results, tracks,
                       ReportContent(sections={"realtime": realtime}),
                       stage=lambda name, k, n: stages.append(name))
    files = rep["files"]
    assert len(files["track_plots"]) == PLOTTED_TRACKS
    assert len(files["deviation_maps"]) <= MAP_LAYERS
    assert len(files["meshes"]) == 14
    ranked = by_severity(rep["tracks"])
    plotted = {int(re.search(r"track_(\d+)_", p).group(1)) for p in files["track_plots"]}
    assert plotted == {t["id"] for t in ranked[:PLOTTED_TRACKS]}
    defects = [t for t in ranked if is_defect(t)]
    assert all(severity(a) >= severity(b) for a, b in zip(defects, defects[1:], strict=False))
    html = (tmp_path / "r" / "index.html").read_text()
    verdict = html[html.index("<section id='verdict'"):html.index("</section>")]
    ids = [int(m) for m in re.findall(r"\(track (\d+)\)", verdict)]
    assert ids == [t["id"] for t in defects[:5]]
    assert f"and {len(defects) - 5} more defect tracks" in verdict
    table = html[html.index("id='tracks'"):]
    table = table[:table.index("</table>")]
    assert table.count("<tr>") == len(tracks) + 1  # header + one row per track
    alarms = html[html.index("id='alarms'"):]
    assert alarms[:alarms.index("</table>")].count("<tr>") == len(realtime["alarms"]) + 1
    assert stages[0] == "meshes" and stages[-1] == "report.json and index.html"
    on_disk = json.loads((tmp_path / "r" / "report.json").read_text())
    assert len(on_disk["tracks"]) == len(tracks)
