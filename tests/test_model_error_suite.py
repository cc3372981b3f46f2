"""The model_error suite: each scenario is a regression scenario on a twin whose physics departs
from the monitor's model, with another seed, and nothing else changed (its faults, part,
process and expectations are the regression scenario's); the suite holds the regression
suite's targets."""

from __future__ import annotations

import tomllib

from dm2.bench.suites import SUITES, resolve_suite
from dm2.core.config import load_scenario
from scenarios import scenario_dir

CHANGED = ("name", "description", "seed", "twin_process")


def test_every_scenario_is_a_regression_scenario_off_the_nominal_model():
    suite, files = resolve_suite("model_error", scenario_dir() / "suites")
    assert suite.targets == SUITES["regression"].targets
    regression = scenario_dir() / "suites" / "regression"
    bases, variants = set(), {}
    for path in files:
        me = tomllib.loads(path.read_text())
        base_name, variant = path.stem.rsplit("_", 1)
        if variant in ("wide", "lean", "rich"):  # two-word variant names
            base_name, first = base_name.rsplit("_", 1)
            variant = f"{first}_{variant}"
        base = tomllib.loads((regression / f"{base_name}.toml").read_text())
        assert me["name"] == f"model_error_{base_name}_{variant}"
        assert me["seed"] == base["seed"] + 1000  # another seed
        assert "twin_process" not in base and me["twin_process"]  # off the nominal model
        assert {k: v for k, v in me.items() if k not in CHANGED} == \
            {k: v for k, v in base.items() if k not in CHANGED}
        load_scenario(path)  # validates every section
        bases.add(base_name)
        variants.setdefault(variant, dict(me["twin_process"]))
        assert variants[variant] == me["twin_process"]  # one physics per variant
    assert len(bases) == 8 and len(files) == 40
    assert variants == {"linear": {"efficiency_curve": "linear"},
                        "logistic": {"efficiency_curve": "logistic", "logistic_k_per_rad": 9.0,
                                     "logistic_phi0_rad": 0.61},
                        "cos_wide": {"efficiency_curve": "cos", "plume_sigma_factor": 1.15},
                        "narrow_lean": {"plume_sigma_factor": 0.85, "efficiency_factor": 0.9},
                        "wide_rich": {"plume_sigma_factor": 1.15, "efficiency_factor": 1.1}}
    assert sum(b.startswith("control_") for b in bases) == 3
