"""``dm2 bench --curve fitted``: each cell's efficiency curve fitted first, then the suite.

A user of a cell whose powder deposits with another efficiency curve than the monitor's model
runs ``dm2 fit-efficiency`` once on a fault-free build (:mod:`dm2.pipeline.curve_fit`) and
monitors every later build with the fitted ``[process] efficiency_cos_exponent``. The bench
rehearses exactly that: for every distinct cell of the suite (the scenario's ``[process]``,
``[twin_process]``, ``[noise]``, ``[cell]`` and ``[monitor]``), a fault-free calibration build
of the hollow seven-sided part (:data:`CALIBRATION_PART`, 3 layers, the scenario's toolpath
settings, seed ``scenario seed + SEED_OFFSET`` of the cell's first scenario) is simulated on the
twin and the exponent fitted from it; each scenario is then monitored with its cell's value.
No scored build is ever used for a fit.
"""

from __future__ import annotations

import json

CALIBRATION_PART = {"generator": "seven_sided",
                    "params": {"height_mm": 2.4, "size_mm": 40.0, "wall_mm": 9.0}}
SEED_OFFSET = 7919
CELL_SECTIONS = ("process", "twin_process", "noise", "cell", "monitor", "toolpath")
TWIN_ONLY = ("faults", "expect", "calibration_error", "duration_s")


def cell_key(sc) -> str:
    """What identifies ``sc``'s cell: its process, physics, noise, cell and monitor tables."""
    d = sc.to_toml_dict()
    return json.dumps({k: d.get(k) for k in CELL_SECTIONS}, sort_keys=True)


def cell_sources(suite_scenarios) -> dict:
    """``{cell_key: scenario}``: the first scenario of each cell in the whole suite's order,
    whose seed the cell's calibration build takes. Computed over the whole suite, so that a run
    of some scenarios (``--only``) monitors each with the curve the full suite gives it."""
    firsts: dict = {}
    for sc in suite_scenarios:
        firsts.setdefault(cell_key(sc), sc)
    return firsts


def calibration_scenario(sc):
    """The fault-free calibration build of ``sc``'s cell (see the module docstring)."""
    from dm2.core.config import parse_scenario

    d = {k: v for k, v in sc.to_toml_dict().items() if k not in TWIN_ONLY}
    d.update(name=f"{sc.name}_curve_calibration", seed=sc.seed + SEED_OFFSET,
             description="fault-free efficiency-curve calibration build",
             part=CALIBRATION_PART)
    d.get("toolpath", {}).pop("max_layers", None)  # the part's height sets the layers
    return parse_scenario(d, f"{sc.name}: curve calibration build")


def fit_cell_curve(sc) -> dict:
    """Simulate ``sc``'s cell's calibration build and fit its exponent; JSON-ready."""
    from dm2.pipeline.curve_fit import fit_efficiency_exponent, recording_pipeline
    from twin.stream.simulate import Simulation

    cal_sc = calibration_scenario(sc)
    sim = Simulation(cal_sc)
    messages = list(sim.messages())
    run = recording_pipeline(lambda: iter(messages), sim.calibration, cal_sc.monitor,
                             cal_sc.cell.plate_size_mm, sim.toolpath)
    fit = fit_efficiency_exponent(run, cal_sc.process)
    return {"calibration_build": cal_sc.name, "seed": cal_sc.seed,
            "exponent": fit.exponent, "start": fit.start,
            "residual_rms_mm": [fit.start_rms_mm, fit.residual_rms_mm],
            "tracks_on_calibration_build": [fit.tracks_at_start, fit.tracks_at_fit],
            "iterations": fit.iterations}


def with_exponent(sc, exponent: float):
    """``sc`` monitored with ``efficiency_cos_exponent = exponent``."""
    process = sc.process.model_copy(update={"efficiency_cos_exponent": float(exponent)})
    return sc.model_copy(update={"process": process})
