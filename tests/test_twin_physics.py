"""[twin_process]: the twin's own physics changes its deposit, never the monitor's reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dm2.core.config import ConfigError, ProcessConfig, parse_scenario
from twin.schema import TwinProcessConfig
from twin.world.deposition import SprayModel, plume_sigma_mm, twin_process
from twin.world.heightfield import HeightField
from twin.world.twin_physics import NOMINAL, TwinPhysics

DT = 1.0 / 250.0
N_STATIC = 250  # 1 s on one spot


def static_spot(physics: TwinPhysics = NOMINAL, process: ProcessConfig | None = None,
                tilt_deg: float = 0.0, spot_z_mm: float = 0.0, seed: int = 5):
    """1 s of spray on one spot of a bare 60 x 60 mm plate; (model, heights (ny, nx), x)."""
    p = process or ProcessConfig()
    hf = HeightField((60.0, 60.0), 0.25, 6.0)
    model = SprayModel(p, seed=seed, physics=physics)
    a = math.radians(tilt_deg)
    axis = np.array([math.sin(a), 0.0, -math.cos(a)])
    model.deposit_samples(hf, np.tile([30.0, 30.0, spot_z_mm], (N_STATIC, 1)),
                          np.tile(axis, (N_STATIC, 1)), DT)
    return model, hf.heights_mm, hf.centres_mm()[0]


def rms_width_mm(h, x) -> float:
    """Per-axis rms width of the deposit along x [mm]."""
    prof = h.sum(axis=0)
    mean = np.average(x, weights=prof)
    return float(math.sqrt(np.average((x - mean) ** 2, weights=prof)))


def fwhm_mm(h, x) -> float:
    """Full width at half maximum of the deposit's x profile through its peak row [mm]."""
    row = h[np.argmax(h.max(axis=1))]
    row = np.convolve(row, np.ones(5) / 5, mode="same")  # packets' shot noise
    above = x[row >= 0.5 * row.max()]
    return float(above.max() - above.min())


def test_twin_process_takes_every_process_key_and_rejects_unknown_ones():
    assert set(ProcessConfig.model_fields) <= set(TwinProcessConfig.model_fields)
    base = {"schema": 1, "name": "t", "part": {"generator": "pad"}}
    sc = parse_scenario({**base, "twin_process": {"feed_g_min": 20.0, "plume_sigma_factor": 1.0,
                                                  "efficiency_factor": 1.0}}, "t.toml")
    proc, _ = twin_process(sc)
    assert sc.process.feed_g_min == 12.0 and proc.feed_g_min == 20.0
    with pytest.raises(ConfigError, match=r"(?s)t.toml.*twin_process.plume_exponet.*unknown key"):
        parse_scenario({**base, "twin_process": {"plume_exponet": 3.0}}, "t.toml")
    with pytest.raises(ConfigError, match=r"plateau_angle_deg 80.0 must be below"):
        parse_scenario({**base, "twin_process": {"plateau_angle_deg": 80.0}}, "t.toml")


def test_default_twin_differs_modestly_from_the_nominal_model():
    sc = parse_scenario({"schema": 1, "name": "t", "part": {"generator": "pad"}}, "t")
    proc, physics = twin_process(sc)
    s_nom, s_twin = plume_sigma_mm(sc.process), plume_sigma_mm(proc)
    assert 0.0 < abs(s_twin / s_nom - 1.0) <= 0.10
    eff = proc.deposition_efficiency / sc.process.deposition_efficiency
    assert 0.0 < abs(eff - 1.0) <= 0.10
    assert physics.efficiency_curve != "cos2"
    assert physics.plume_exponent != 2.0 and physics.porosity > 0
    assert physics.standoff_efficiency_per_mm != 0.0


def test_sigma_and_efficiency_factors_change_width_and_mass():
    sc = parse_scenario({"schema": 1, "name": "t", "part": {"generator": "pad"},
                         "twin_process": {"plume_sigma_factor": 1.15, "efficiency_factor": 0.85,
                                          "efficiency_curve": "cos2", "plume_exponent": 2.0,
                                          "porosity": 0.0, "standoff_efficiency_per_mm": 0.0}},
                        "t")
    proc, physics = twin_process(sc)
    nom, h0, x = static_spot()
    twin, h1, _ = static_spot(physics, proc)
    assert twin.deposited_mass_g / nom.deposited_mass_g == pytest.approx(0.85, rel=0.02)
    assert rms_width_mm(h1, x) / rms_width_mm(h0, x) == pytest.approx(1.15, rel=0.03)


@pytest.mark.parametrize("curve, expected", [
    ("cos2", math.cos(0.5 * math.pi * 0.64) ** 2), ("cos", 0.5),
    ("linear", 1.0 - 60.0 / 75.0), ("plateau", 1.0 - 30.0 / 45.0)])
def test_efficiency_curve_shape_sets_the_mass_of_a_60_degree_spray(curve, expected):
    nom, _, _ = static_spot(tilt_deg=60.0)
    model, _, _ = static_spot(TwinPhysics(efficiency_curve=curve), tilt_deg=60.0)
    ratio = model.deposited_volume_mm3 / model.fed_volume_mm3 / 0.5
    assert ratio == pytest.approx(expected, rel=0.02)
    if curve != "cos2":
        assert abs(model.deposited_mass_g / nom.deposited_mass_g - 1.0) > 0.05


def test_super_gaussian_plume_keeps_rms_width_and_mass_but_widens_the_top():
    _, h0, x = static_spot()
    m3, h3, _ = static_spot(TwinPhysics(plume_exponent=3.0))
    nom, _, _ = static_spot()
    assert m3.deposited_mass_g == pytest.approx(nom.deposited_mass_g, rel=0.01)
    assert rms_width_mm(h3, x) == pytest.approx(rms_width_mm(h0, x), rel=0.03)
    # exp(-(r/a)^3 / 2) at the Gaussian's rms: FWHM 1.13 times the Gaussian's
    assert fwhm_mm(h3, x) / fwhm_mm(h0, x) > 1.08
    assert h3.max() < 0.95 * h0.max()  # the same mass, spread over a flatter top


def test_porosity_raises_the_deposit_at_equal_mass():
    nom, h0, _ = static_spot()
    por, h1, _ = static_spot(TwinPhysics(porosity=0.1))
    assert por.deposited_mass_g == pytest.approx(nom.deposited_mass_g, rel=0.01)
    assert h1.sum() / h0.sum() == pytest.approx(1.0 / 0.9, rel=0.01)


def test_standoff_dependent_efficiency_follows_the_flight_to_the_surface():
    physics = TwinPhysics(standoff_efficiency_per_mm=-0.01)
    at_standoff, _, _ = static_spot(physics)
    nom, _, _ = static_spot()
    assert at_standoff.deposited_mass_g == pytest.approx(nom.deposited_mass_g, rel=0.01)
    # the surface lies 8 mm below the programmed spot: the packets fly 38 mm, not 30
    far, _, _ = static_spot(physics, spot_z_mm=8.0)
    far_nom, _, _ = static_spot(spot_z_mm=8.0)
    assert far.deposited_mass_g / far_nom.deposited_mass_g == pytest.approx(0.92, rel=0.01)
