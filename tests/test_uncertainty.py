"""Uncertainty-aware classification: the same deviation is a defect on a well observed flat
top and uncertain at a wall; the model's coefficients are recovered from fault-free data."""

from types import SimpleNamespace

import numpy as np
import pytest

from dm2.core.config import MonitorConfig
from dm2.defects.classify import OVERBUILD, UNCERTAIN, UNDERBUILD, classify_vertices
from dm2.defects.deviation import layer_deviation
from dm2.defects.uncertainty import FEATURES, coefficients, vertex_sigma_mm
from dm2.defects.uncertainty_fit import fit_coefficients, fit_uncertainty
from dm2.reference.height_map import ReferenceMap

MON = MonitorConfig()
CELL = 0.5


def grid(n=60, step=0.5):
    x = np.arange(n) * step
    xx, yy = np.meshgrid(x, x)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(),
                  idx[1:, 1:].ravel())
    faces = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    return np.column_stack([xx.ravel(), yy.ravel(), np.zeros(n * n)]), faces, xx, yy


def test_bound_decides_the_defect_and_the_tolerance_its_extent():
    v, faces, xx, yy = grid()
    d = np.zeros(xx.shape)
    sigma = np.full(xx.shape, 0.1)
    a = (xx < 5) & (yy < 5)  # 0.5 mm over, well within the bound: a defect
    b = (xx > 20) & (yy < 5)  # 0.5 mm over where the model is unsure: uncertain
    c = (xx < 10) & (yy > 15)  # unsure except a 2 x 2 mm core: a defect as far as it reaches
    d[a | b | c] = 0.5
    sigma[b | c] = 0.3
    sigma[c & (xx < 2) & (yy > 27)] = 0.1
    d[(xx > 20) & (yy > 20)] = -0.9  # an isolated underbuild beyond its bound
    c_ = classify_vertices(v, faces, np.full(d.size, 5.0), d.ravel(), MON,
                           sigma_mm=sigma.ravel()).class_code.reshape(xx.shape)
    assert np.all(c_[a] == OVERBUILD) and np.all(c_[c] == OVERBUILD)
    assert np.all(c_[b] == UNCERTAIN)
    assert np.all(c_[(xx > 20) & (yy > 20)] == UNDERBUILD)
    # without the bound: the paper's rule alone
    plain = classify_vertices(v, faces, np.full(d.size, 5.0), d.ravel(), MON).class_code
    assert np.all(plain.reshape(xx.shape)[b] == OVERBUILD)


def test_sigma_grows_at_walls_feet_and_low_weight():
    f = np.zeros((4, len(FEATURES)))
    f[:, 0] = 1.0
    f[:, 1] = [1 / 8, 1 / 8, 1 / 8, 1.0]
    f[1, 2] = 1.0  # vertical wall
    f[2, 4] = 1.0  # foot of a wall
    s = vertex_sigma_mm(f, MON.uncertainty)
    u = MON.uncertainty
    assert s[0] == pytest.approx(np.hypot(u.floor_mm, u.range_mm / np.sqrt(8)))
    assert s[1] == pytest.approx(np.sqrt(s[0] ** 2 + u.wall_mm ** 2))
    assert s[2] == pytest.approx(np.sqrt(s[0] ** 2 + u.foot_mm ** 2))
    assert s[3] == pytest.approx(np.hypot(u.floor_mm, u.range_mm))


def test_coefficients_recovered_from_fault_free_deviations():
    rng = np.random.default_rng(4)
    n = 200_000
    f = np.column_stack([np.ones(n), 1 / rng.uniform(1, 8, n), rng.uniform(0, 1, n) ** 2,
                         (rng.random(n) < 0.1) * rng.uniform(0, 1, n) ** 2,
                         (rng.random(n) < 0.1) * 1.0, rng.uniform(0, 2, n) ** 2,
                         rng.uniform(0, 1.2, n) ** 2, rng.uniform(0, 3, n) ** 2])
    true = np.array([0.08, 0.2, 0.3, 0.15, 0.25, 0.1, 0.2, 0.12]) ** 2
    d = rng.normal(0.0, np.sqrt(f @ true))
    got = np.sqrt(fit_coefficients(f, d))
    assert got == pytest.approx(np.sqrt(true), rel=0.1)
    # an excluded feature (a prior) keeps its given value; the others are fitted around it
    fixed = np.zeros(len(FEATURES))
    fixed[7] = true[7]
    kept = np.sqrt(fit_coefficients(f, d, exclude=("plume",), fixed=fixed))
    assert kept[7] == np.sqrt(true[7])
    assert kept == pytest.approx(np.sqrt(true), rel=0.1)


def test_fit_on_a_noisy_fault_free_top_gives_its_noise_as_floor():
    rng = np.random.default_rng(1)
    n = 241
    c = (np.arange(n) + 0.5) * CELL
    ref = ReferenceMap(np.full((n, n), 2.0), CELL, layer=2)
    x = np.linspace(20.0, 100.0, 161)
    xx, yy = np.meshgrid(x, x)
    noise_mm = 0.12
    z = 2.0 + rng.normal(0.0, noise_mm, xx.size)
    idx = np.arange(xx.size).reshape(xx.shape)
    a, b, cc, dd = (idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(),
                    idx[1:, 1:].ravel())
    surf = SimpleNamespace(vertices_O=np.column_stack([xx.ravel(), yy.ravel(), z]),
                           faces=np.concatenate([np.column_stack([a, b, dd]),
                                                 np.column_stack([a, dd, cc])]),
                           weight=np.full(xx.size, 8.0),
                           normals_O=np.tile([0.0, 0.0, 1.0], (xx.size, 1)))
    dev = layer_deviation(surf, ref, MON, 2)
    fit = fit_uncertainty([SimpleNamespace(deviation=dev, reference=ref)], MON)
    total = np.sqrt(fit["floor_mm"] ** 2 + fit["range_mm"] ** 2 / 8)
    assert total == pytest.approx(noise_mm, rel=0.05)
    assert fit["wall_mm"] < 0.05 and fit["foot_mm"] < 0.05 and fit["height_mm"] < 0.05
    assert coefficients(MON.uncertainty).shape == (len(FEATURES),) and c.size == n


def test_plume_sensitivity_is_how_the_reference_moves_with_its_plume_width():
    # a straight pass of constant mass per length: a Gaussian ridge of width sigma; a plume 2 %
    # wider lowers its crest and raises its flanks by sigma^2 h'' * ln(1.02) (heat equation)
    cell, sigma, mass = 0.25, 2.95, 6.0
    x = (np.arange(160) + 0.5) * cell - 20.0

    def ridge(s):
        return np.tile(mass / (np.sqrt(2 * np.pi) * s) * np.exp(-x * x / (2 * s * s)), (40, 1))

    ref = ReferenceMap(ridge(sigma), cell, plume_sigma_mm=sigma)
    xy = np.column_stack([(np.arange(40, 120) + 0.5) * cell, np.full(80, 5.0)])  # x -10..10
    from dm2.reference.height_map import bilinear_height

    moved = bilinear_height(ridge(sigma * 1.02) - ridge(sigma), cell, xy) / np.log(1.02)
    got = ref.plume_sensitivity_at(xy, smooth_mm=0.05)
    assert np.abs(got - moved).max() < 0.02 * np.abs(moved).max()
    assert got[40] < 0 and got[10] > 0  # the crest comes down, the flanks go up
    # a flat top does not move; a reference of unknown plume width has no sensitivity
    flat = ReferenceMap(np.full((40, 40), 2.0), cell, plume_sigma_mm=sigma)
    assert np.abs(flat.plume_sensitivity_at(xy[:5] + 10.0)).max() < 1e-9
    assert np.all(ReferenceMap(ridge(sigma), cell).plume_sensitivity_at(xy) == 0.0)
