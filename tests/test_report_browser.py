"""The inspection sheet and the 3D view, rendered in headless Chromium (Debian's ``chromium``;
``.ci/run`` installs it, so these tests always run).

A short pad run with a 1 mm bump from layer 2 and the same run without the fault: the verdict
opens with the bump's kind, place and first layer, is the monitor's own (unchanged once the
twin's truth is deleted and the page re-rendered) and fits the first 1400 x 900 screen. A
monitored run without any deviation reads "No defect found", and so does the fault-free twin
control under the twin's default model error. ``dm2 view`` serves the bump run: its 3D
canvas draws the part (the bump in the red of positive deviation) and shows the layer slider.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from chromium import Browser, free_port
from typer.testing import CliRunner

from dm2.cli.main import app

BUMP = {"kind": "bump", "center_O_mm": [57.0, 60.0], "height_mm": 1.0, "width_mm": 5.0,
        "layers": [2, 2]}


def _scenario(tmp: Path, name: str, faults: list[dict]) -> Path:
    lines = [f'schema = 1\nname = "{name}"\nseed = 5\nduration_s = 30.0\n[part]\n'
             'generator = "pad"\n[toolpath]\ncontour_angle_deg = 0.0\n[process]\n'
             "feed_g_min = 26.0\n"]
    for f in faults:
        lines.append("[[faults]]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in f.items()))
    path = tmp / f"{name}.toml"
    path.write_text("".join(lines))
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("runs")
    out = {}
    for name, faults in (("bump", [BUMP]), ("control", [])):
        res = CliRunner().invoke(app, ["run", str(_scenario(tmp, f"pad_{name}", faults)),
                                       "--out", str(tmp / name), "--no-record"])
        assert res.exit_code == 0, res.output
        out[name] = tmp / name
        out[f"{name}_console"] = res.output
    return out


VERDICT_JS = "document.getElementById('verdict').innerText"


def _sheet(path: Path) -> dict:
    with Browser(path.as_uri(), 1400, 900) as b:
        b.wait_for("document.readyState == 'complete' && !!document.getElementById('verdict')")
        return b.evaluate(
            "(() => {const v = document.getElementById('verdict').getBoundingClientRect();"
            "const o = document.querySelector('#overview img');"
            f"return {{verdict: {VERDICT_JS}, bottom: v.bottom, top: v.top,"
            "overview: o ? o.naturalWidth : 0, timeline: !!document.querySelector("
            "'#timeline img'), truth: document.body.innerText.includes('Injected faults'),"
            "height: window.innerHeight}})()")


def test_verdict_names_the_bump_and_comes_from_the_monitor(runs):
    run = runs["bump"]
    page = _sheet(run / "index.html")
    assert page["height"] == 900 and 0 <= page["top"] and page["bottom"] <= 900
    first = [line for line in page["verdict"].splitlines() if line.strip()]
    assert " in 5 layers" in first[0], page["verdict"]
    assert first[1].startswith("Overbuild at (") and "from layer 2" in first[1], first
    x, y = (float(c) for c in first[1].split("(")[1].split(")")[0].split(","))
    assert np.hypot(x - 57.0, y - 60.0) < 3.0
    assert page["overview"] > 0 and page["timeline"] and page["truth"]
    shutil.rmtree(run / "truth")
    res = CliRunner().invoke(app, ["report", str(run)])
    assert res.exit_code == 0, res.output
    again = _sheet(run / "index.html")
    assert again["verdict"] == page["verdict"] and not again["truth"]
    console = runs["bump_console"]
    assert "new track #" in console and "overbuild at (" in console
    assert "real-time:" not in console  # alarms are in run.log and the report
    assert "real-time: overbuild" in (run / "run.log").read_text()


def test_a_run_without_deviation_reads_no_defect_found(tmp_path):
    from test_deviation import CELL, MON, pad_heights, top_surface

    from dm2.defects.layer_analysis import LayerAnalysis
    from dm2.reference.height_map import ReferenceMap
    from dm2.report import write_report

    mon = LayerAnalysis(MON)
    for layer in range(4):
        ref_h, _, _ = pad_heights(layer)
        mon.analyse_layer(top_surface(ref_h), ReferenceMap(ref_h, CELL, layer))
    mon.finish()
    write_report(tmp_path / "r", mon.results, mon.tracker.tracks)
    page = _sheet(tmp_path / "r" / "index.html")
    assert page["verdict"].strip() == "No defect found in 4 layers; 0 regions uncertain."
    assert page["overview"] > 0 and page["bottom"] <= 900


def test_fault_free_control_reads_no_defect_found(runs):
    page = _sheet(runs["control"] / "index.html")
    assert page["overview"] > 0 and page["bottom"] <= 900
    assert page["verdict"].startswith("No defect found in 5 layers"), page["verdict"]


def test_dm2_view_draws_the_part_and_the_layer_slider(runs):
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "dm2.cli.main", "view", str(runs["bump"]),
                             "--port", str(port)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 120
        seen = ""
        while f"127.0.0.1:{port}" not in seen or "Ctrl-C" not in seen:
            line = proc.stdout.readline()
            assert line or proc.poll() is None, seen
            seen += line
            assert time.monotonic() < deadline, seen
        with Browser(f"http://127.0.0.1:{port}", 1400, 900) as b:
            sliders = b.wait_for("document.querySelector('canvas') && Array.from("
                                 "document.querySelectorAll('[role=slider]')).map("
                                 "e => e.getAttribute('aria-valuemax'))", 90)
            assert "4" in sliders  # layers 0..4
            assert "layer" in b.evaluate("document.body.innerText")
            red = 0
            for _ in range(60):  # the scene arrives over the websocket, then draws
                img = b.screenshot()
                canvas = img[200:800, 150:1000]  # left of the control panel
                red = int(np.sum((canvas[..., 0] > 0.6) & (canvas[..., 2] < 0.5)
                                 & (canvas[..., 1] < 0.5)))
                drawn = int(np.sum(np.abs(canvas - canvas[0, 0]).sum(axis=-1) > 0.05))
                if red > 20 and drawn > 2000:
                    break
                time.sleep(1.0)
            assert drawn > 2000 and red > 20, (drawn, red)
    finally:
        proc.terminate()
        proc.wait(20)
