"""The dirty suite: each scenario is a regression scenario seen by the realistic sensor preset,
with another seed, and nothing else changed; at least 8 scenarios on at least 3 parts, at least
3 fault-free controls; the regression suite's targets."""

from __future__ import annotations

import tomllib

from dm2.bench.suites import SUITES, resolve_suite
from dm2.core.config import load_scenario
from scenarios import scenario_dir
from twin.schema import NOISE_PRESETS

CHANGED = ("name", "description", "seed", "noise")


def test_every_scenario_is_a_regression_scenario_on_dirty_sensors():
    suite, files = resolve_suite("dirty", scenario_dir() / "suites")
    assert suite.targets == SUITES["regression"].targets
    regression = scenario_dir() / "suites" / "regression"
    parts = set()
    for path in files:
        dirty = tomllib.loads(path.read_text())
        base = tomllib.loads((regression / path.name).read_text())
        assert dirty["name"] == f"dirty_{path.stem}"
        assert dirty["seed"] == base["seed"] + 1000
        assert dirty["noise"] == {"preset": "realistic"}
        assert {k: v for k, v in dirty.items() if k not in CHANGED} == \
            {k: v for k, v in base.items() if k not in CHANGED}
        sc = load_scenario(path)
        for key, value in NOISE_PRESETS["realistic"].items():
            assert getattr(sc.noise, key) == value
        parts.add(str(dirty["part"]))
    assert len(files) >= 8 and len(parts) >= 3
    assert sum(p.stem.startswith("control_") for p in files) >= 3
