"""The twin's logistic efficiency curve ([twin_process] efficiency_curve = "logistic"):
expit(k (phi - phi0)) in the spray angle phi between jet and surface, 1 at normal impact, no
cut at the critical angle; k and phi0 settable."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import expit
from test_twin_physics import static_spot

from dm2.core.config import ConfigError, parse_scenario
from twin.world.deposition import twin_process
from twin.world.twin_physics import TwinPhysics


def logistic(tilt_deg, k=9.0, phi0=0.61):
    phi = math.radians(90.0 - tilt_deg)
    return float(expit(k * (phi - phi0)) / expit(k * (0.5 * math.pi - phi0)))


@pytest.mark.parametrize("tilt_deg, k, phi0", [(60.0, 9.0, 0.61), (60.0, 20.0, 0.61),
                                               (45.0, 9.0, 0.9)])
def test_logistic_curve_sets_the_mass_of_a_tilted_spray(tilt_deg, k, phi0):
    """The deposited share of the fed volume at a tilted spray on a bare plate is the nominal
    0.5 efficiency times the logistic at that spray angle (0.315 at 60 deg off normal with the
    defaults, 0.151 with k = 20, 0.258 at 45 deg with phi0 = 0.9 rad)."""
    phys = TwinPhysics(efficiency_curve="logistic", logistic_k_per_rad=k, logistic_phi0_rad=phi0)
    model, _, _ = static_spot(phys, tilt_deg=tilt_deg)
    expected = logistic(tilt_deg, k, phi0)
    assert model.deposited_volume_mm3 / model.fed_volume_mm3 / 0.5 == pytest.approx(
        expected, rel=0.02)
    theta = np.radians([0.0, tilt_deg, 80.0, 90.0])
    np.testing.assert_allclose(phys.relative_efficiency(theta, 75.0),
                               [1.0, expected, logistic(80.0, k, phi0), 0.0], atol=1e-12)


def test_logistic_curve_has_no_cut_at_the_critical_angle():
    """80 deg off normal lies beyond the 75 deg critical angle: every named curve deposits
    nothing there, the logistic still its 2 % (expit(9 (0.175 - 0.61)))."""
    model, _, _ = static_spot(TwinPhysics(efficiency_curve="logistic"), tilt_deg=80.0)
    share = model.deposited_volume_mm3 / model.fed_volume_mm3 / 0.5
    assert share == pytest.approx(logistic(80.0), abs=0.003) and share > 0.015
    plateau, _, _ = static_spot(TwinPhysics(efficiency_curve="plateau"), tilt_deg=80.0)
    assert plateau.deposited_volume_mm3 == 0.0


def test_the_scenario_sets_the_logistic_and_refuses_a_bad_midpoint():
    base = {"schema": 1, "name": "t", "part": {"generator": "pad"}}
    sc = parse_scenario({**base, "twin_process": {"efficiency_curve": "logistic",
                                                  "logistic_k_per_rad": 12.0,
                                                  "logistic_phi0_rad": 0.5}}, "t.toml")
    _, physics = twin_process(sc)
    assert (physics.efficiency_curve, physics.logistic_k_per_rad,
            physics.logistic_phi0_rad) == ("logistic", 12.0, 0.5)
    _, default = twin_process(parse_scenario({**base, "twin_process": {
        "efficiency_curve": "logistic"}}, "t.toml"))
    assert (default.logistic_k_per_rad, default.logistic_phi0_rad) == (9.0, 0.61)
    with pytest.raises(ConfigError, match=r"(?s)t.toml.*twin_process.logistic_phi0_rad"):
        parse_scenario({**base, "twin_process": {"logistic_phi0_rad": 2.0}}, "t.toml")
