"""The shapes suite: a fault-free control of each part shape the monitor was not developed on,
and faults placed on those parts; the suite holds the regression suite's targets."""

from __future__ import annotations

import tomllib

import shapely

from dm2.bench.suites import SUITES, resolve_suite
from dm2.core.config import load_scenario
from dm2.toolpath.slicing import slice_mesh
from scenarios import scenario_dir
from scenarios.parts import build_part

SHAPES = {"cylinder", "ring", "tee", "triangle"}
PLATE = (120.0, 120.0, 6.0)  # the cell's default plate (no scenario of the suite sets one)


def test_every_shape_has_a_control_and_the_faults_lie_on_their_parts():
    suite, files = resolve_suite("shapes", scenario_dir() / "suites")
    assert suite.targets == SUITES["regression"].targets
    controls, faulty = set(), set()
    for path in files:
        raw = tomllib.loads(path.read_text())
        assert "twin_process" not in raw and "cell" not in raw  # the twin's defaults, as regression
        sc = load_scenario(path)
        assert sc.name == f"shapes_{path.stem}" and sc.part.generator in SHAPES
        if not raw.get("faults"):
            assert sc.expect.no_tracks and sc.expect.no_local_tracks
            controls.add(sc.part.generator)
            continue
        faulty.add(sc.part.generator)
        first = slice_mesh(build_part(sc.part, PLATE), 0.8).regions[0]
        for fault in raw["faults"]:
            if "center_O_mm" in fault:  # a local fault: on the part (an edge counts)
                assert first.buffer(1e-6).contains(shapely.Point(fault["center_O_mm"]))
    assert controls == SHAPES and faulty == SHAPES and len(files) == 8
