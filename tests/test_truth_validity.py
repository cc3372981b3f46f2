"""The twin's validity gate on its own truth: steep faces over the plume's width, features
narrower than the plume's sigma, mass balance; an unstable deposition trips it, the bench
does not score a run outside it."""

from __future__ import annotations

import math

import numpy as np

from dm2.bench.scoring import truth_invalid
from dm2.core.config import ProcessConfig
from twin.world.deposition import SprayModel
from twin.world.heightfield import HeightField
from twin.world.validity import check_truth

CELL = 0.25
SIGMA = 3.0
LAYER = 0.8


def _cone(height_mm: float, flank_deg: float) -> np.ndarray:
    y, x = (np.indices((160, 160)) + 0.5) * CELL
    r = np.hypot(x - 20.0, y - 20.0)
    return np.maximum(height_mm - r * math.tan(math.radians(flank_deg)), 0.0)


def _check(H, gain=100.0, stuck=100.0, fed=200.0, planned=200.0):
    return check_truth(H, CELL, sigma_mm=SIGMA, layer_mm=LAYER, critical_angle_deg=75.0,
                       field_gain_mm3=gain, stuck_mm3=stuck, fed_mm3=fed,
                       planned_fed_mm3=planned, planned_top_mm=10.0)


def test_a_sprayed_cone_is_valid_and_a_needle_on_it_is_not():
    cone = _cone(10.0, 60.0)
    ok = _check(cone)
    assert ok["valid"] and ok["reasons"] == [] and ok["narrow_feature_rise_mm"] < 1e-9
    assert math.isclose(ok["true_top_mm"], cone.max()) and ok["efficiency"] == 0.5
    needle = cone.copy()
    needle[80, 80] += 2.0  # one node 2 mm above the cone's tip
    bad = _check(needle)
    assert not bad["valid"] and len(bad["reasons"]) == 1
    assert "narrower than the plume's sigma" in bad["reasons"][0]
    assert 1.0 < bad["narrow_feature_rise_mm"] <= 2.0 + 1e-9


def test_a_face_steeper_than_the_critical_angle_over_the_plume_width_is_invalid():
    wall = np.zeros((160, 160))
    wall[:, 60:100] = 30.0  # 30 mm vertical faces: 30 mm over 6 mm is 79 deg
    r = _check(wall)
    assert not r["valid"] and r["steepest_slope_deg"] > 75.0
    assert any("steepest slope" in s for s in r["reasons"])


def test_mass_balance_off_by_more_than_one_percent_is_invalid():
    cone = _cone(10.0, 60.0)
    assert _check(cone, gain=100.9)["valid"]
    r = _check(cone, gain=102.0)
    assert not r["valid"] and len(r["reasons"]) == 1 and "2.00 % off" in r["reasons"][0]
    r = _check(cone, fed=195.0)
    assert not r["valid"] and "feed x time" in r["reasons"][0]


def _spray_on_bump(unstable: bool) -> dict:
    """A 1 mm Gaussian bump sprayed by a jet tilted 35 degrees from four sides, 20 s in all."""
    p = ProcessConfig(feed_g_min=26.0)
    hf = HeightField(size_mm=(40.0, 40.0), cell_mm=CELL, thickness_mm=6.0)
    x, y = hf.centres_mm()
    hf.heights_mm = np.outer(np.exp(-(y - 20) ** 2 / 2), np.exp(-(x - 20) ** 2 / 2))
    start_mm3 = float(hf.heights_mm.sum()) * CELL * CELL
    model = SprayModel(p, seed=5)
    if unstable:  # a normal over no span: every face reads flat
        base = model._plume
        model._plume = lambda f: base(f)._replace(normal_cells=0)
    t = math.radians(35.0)
    for _ in range(10):
        for k in range(4):
            az = k * math.pi / 2
            axis = np.array([math.sin(t) * math.cos(az), math.sin(t) * math.sin(az),
                             -math.cos(t)])
            model.deposit(hf, np.array([20.0, 20.0, hf.heights_mm.max()]), axis, dt_s=0.5)
    H = hf.heights_mm
    return check_truth(H, CELL, sigma_mm=model.sigma_mm(), layer_mm=LAYER,
                       critical_angle_deg=p.critical_angle_deg,
                       field_gain_mm3=float(H.sum()) * CELL * CELL - start_mm3,
                       stuck_mm3=model.deposited_volume_mm3, fed_mm3=model.fed_volume_mm3,
                       planned_fed_mm3=model.fed_volume_mm3)


def test_an_unstable_deposition_trips_the_gate_and_the_default_does_not():
    ok = _spray_on_bump(unstable=False)
    assert ok["valid"], ok["reasons"]
    assert ok["field_vs_stuck_error"] < 1e-9
    bad = _spray_on_bump(unstable=True)
    assert not bad["valid"]
    assert [s for s in bad["reasons"] if "narrower than the plume's sigma" in s]
    assert bad["narrow_feature_rise_mm"] > LAYER


def test_the_bench_reads_an_invalid_truth_as_not_to_be_scored():
    assert truth_invalid(None) == [] and truth_invalid({"valid": True, "reasons": []}) == []
    reasons = ["a feature narrower than the plume's sigma (2.95 mm) stands 40.00 mm above"]
    assert truth_invalid({"valid": False, "reasons": reasons}) == reasons
