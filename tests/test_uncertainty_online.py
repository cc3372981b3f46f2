"""The uncertainty's model-error terms follow what the layer itself shows: a systematic model
error over a term's whole bin raises that term by the injected factor, a cell closer to the
model than the fit lowers it, at most to half; a local defect in a
minority of the bin, a global offset of the top and a small bin do not; the live columns take
the factors and give them back."""

import numpy as np
import pytest

from dm2.core.config import MonitorConfig
from dm2.defects.realtime import RealtimeDeviation
from dm2.defects.uncertainty import FEATURES, coefficients
from dm2.defects.uncertainty_online import (
    FACTORS,
    MAX_INFLATION,
    MIN_BIN_VERTICES,
    MIN_FACTOR,
    inflated_sigma_mm,
    live_factors,
    model_inflation,
)

MON = MonitorConfig()
COEF = coefficients(MON.uncertainty)
PLUME = FEATURES.index("plume")
WALL = FEATURES.index("wall")


def layer(rng, n_top=4000, n_edge=800, n_wall=600):
    """Features of a layer: a top (floor and range only), edges where the plume term
    dominates (plume sensitivity 2 mm) and walls (measured |n_z| near 0)."""
    f = np.zeros((n_top + n_edge + n_wall, len(FEATURES)))
    f[:, 0] = 1.0
    f[:, 1] = 1.0
    f[n_top:n_top + n_edge, PLUME] = 4.0  # P = 2 mm: sigma_plume 0.2 mm against 0.17 mm
    f[n_top + n_edge:, WALL] = 0.8
    sigma = np.sqrt(f @ COEF)
    return f, sigma, slice(0, n_top), slice(n_top, n_top + n_edge), slice(n_top + n_edge, None)


def inflate(f, d, observed=None, concave=None):
    """model_inflation with every vertex observed and convex unless given."""
    n = len(d)
    return model_inflation(f, d, COEF, np.ones(n, bool) if observed is None else observed,
                           np.zeros(n, bool) if concave is None else concave)


def term_error(rng, f, sigma, rows, term, true_factor):
    """Deviations at ``rows`` whose ``term`` spread is ``true_factor`` times the configured one
    (the other terms as configured): ``(d (k,), term_sd, other_sd, whole)``, ``whole`` the RMS of
    the bin's z that this gives (between 1 and the term's own factor)."""
    term_sd = np.sqrt(f[rows, term] * COEF[term])
    other_sd = np.sqrt(sigma[rows] ** 2 - term_sd ** 2)
    d = (rng.normal(0.0, 1.0, term_sd.size) * true_factor * term_sd
         + rng.normal(0.0, 1.0, term_sd.size) * other_sd)
    whole = np.sqrt(np.mean((true_factor * term_sd) ** 2 + other_sd ** 2)
                    / np.mean(sigma[rows] ** 2))
    return d, term_sd, other_sd, whole


def test_deviations_the_model_explains_raise_nothing():
    rng = np.random.default_rng(1)
    f, sigma, *_ = layer(rng)
    d = rng.normal(0.0, 1.0, len(sigma)) * sigma
    factor = inflate(f, d)
    assert set(factor) == set(FACTORS)
    assert all(v < 1.1 for v in factor.values())  # a bin's median of z^2 scatters a little
    assert np.array_equal(inflated_sigma_mm(f, COEF, dict.fromkeys(FACTORS, 1.0),
                                            np.zeros(len(d), bool)), sigma)  # bit for bit

@pytest.mark.parametrize("true_factor", [1.8, 2.5])
def test_systematic_model_error_at_the_edges_is_recovered(true_factor):
    rng = np.random.default_rng(2)
    f, sigma, top, edge, wall = layer(rng)
    d = rng.normal(0.0, 1.0, len(sigma)) * sigma
    # the cell's edges: the plume term's spread is true_factor times the configured one
    d[edge], plume_sd, _, whole = term_error(rng, f, sigma, edge, PLUME, true_factor)
    concave = np.zeros(len(d), bool)
    concave[edge] = True  # the cell errs where the reference is concave (feet, hole rims)
    factor = inflate(f, d, concave=concave)
    # the bin's robust RMS of z mixes the plume term with the others: between the true factor
    # of the whole sigma and the plume term's own
    assert whole * 0.9 < factor["plume_concave"] < true_factor * 1.1
    assert factor["plume_convex"] == 1.0  # no vertices there: no evidence
    assert factor["wall"] == pytest.approx(1.0, abs=0.05)  # the walls as the model predicts
    # the raised sigma: the plume term's variance times the factor squared, concave only
    raised = inflated_sigma_mm(f, COEF, factor, concave)
    assert raised[edge] == pytest.approx(np.sqrt(sigma[edge] ** 2 + (factor["plume_concave"] ** 2
                                                                     - 1) * plume_sd ** 2))
    assert np.array_equal(raised[top], sigma[top])
    # the same error at convex vertices raises the convex bin instead
    swapped = inflate(f, d)
    assert swapped["plume_convex"] == factor["plume_concave"]
    assert swapped["plume_concave"] == 1.0


@pytest.mark.parametrize("true_factor", [0.7, 0.2])
def test_walls_closer_to_the_model_than_the_fit_lower_their_term_at_most_to_half(true_factor):
    rng = np.random.default_rng(5)
    f, sigma, top, edge, wall = layer(rng)
    d = rng.normal(0.0, 1.0, len(sigma)) * sigma
    d[wall], wall_sd, other_sd, whole = term_error(rng, f, sigma, wall, WALL, true_factor)
    factor = inflate(f, d)
    # the bin's RMS of z: the whole sigma's share that is left, bounded below by MIN_FACTOR
    assert factor["wall"] == pytest.approx(max(whole, MIN_FACTOR), abs=0.05)
    assert factor["wall"] >= MIN_FACTOR and factor["wall"] < 0.95
    assert factor["plume_convex"] == pytest.approx(1.0, abs=0.1)  # the edges as predicted
    lowered = inflated_sigma_mm(f, COEF, factor, np.zeros(len(d), bool))
    assert lowered[wall] == pytest.approx(np.sqrt(other_sd ** 2
                                                  + (factor["wall"] * wall_sd) ** 2))
    assert np.array_equal(lowered[top], sigma[top])  # floor and range stay as configured


def test_a_local_defect_and_a_global_offset_raise_nothing_much():
    rng = np.random.default_rng(3)
    f, sigma, top, edge, wall = layer(rng)
    d = rng.normal(0.0, 1.0, len(sigma)) * sigma
    d[top] += 0.8  # the whole top 0.8 mm over: the process fit's business, not the bound's
    e = np.arange(len(d))[edge]
    d[e[:40]] -= 1.5  # a dent on 5 % of the edges
    d[np.arange(len(d))[wall][:30]] += 1.5  # a bump on 5 % of the walls
    factor = inflate(f, d)
    assert all(v < 1.1 for v in factor.values())
    # so the dent still stands far beyond the (hardly raised) bound
    raised = inflated_sigma_mm(f, COEF, factor, np.zeros(len(d), bool))
    assert np.mean(np.abs(d[e[:40]]) > 3.0 * raised[e[:40]]) > 0.95


def test_small_bins_and_unobserved_vertices_say_nothing_and_the_factor_is_capped():
    rng = np.random.default_rng(4)
    f, sigma, top, edge, wall = layer(rng, n_edge=MIN_BIN_VERTICES - 1)
    d = rng.normal(0.0, 1.0, len(sigma)) * sigma
    d[edge] *= 10.0
    assert inflate(f, d)["plume_convex"] == 1.0
    f, sigma, top, edge, wall = layer(rng)
    d = rng.normal(0.0, 1.0, len(sigma)) * sigma
    d[edge] *= 10.0
    assert inflate(f, d)["plume_convex"] == MAX_INFLATION
    observed = np.ones(len(d), bool)
    observed[edge] = False  # the same error where nothing was observed: no evidence
    assert inflate(f, d, observed=observed)["plume_convex"] == 1.0


def test_live_columns_take_the_factors_and_give_them_back():
    rt = RealtimeDeviation(MON)
    u = MON.uncertainty
    factors = {"wall": 2.0, "edge": 1.5, "foot": 3.0, "plume_concave": 2.5, "plume_convex": 1.2}
    assert live_factors(factors) == {"wall": 2.0, "edge": 1.5, "plume": 2.5}  # the larger
    rt.set_model_inflation(live_factors(factors))
    assert rt._bound[3] == pytest.approx(2.0 * u.wall_mm)
    assert rt._edge_mm == pytest.approx(1.5 * u.edge_mm)
    assert rt._plume_rel == pytest.approx(2.5 * u.plume_rel)
    assert rt._params[3] == rt._bound and rt._params[4] == rt._edge_mm  # CompareParams
    rt.set_model_inflation(None)
    assert rt._bound[3] == u.wall_mm and rt._edge_mm == u.edge_mm
    assert rt._plume_rel == u.plume_rel
    plain = RealtimeDeviation(MON, uncertainty=False)
    plain.set_model_inflation(live_factors(factors))
    assert plain._bound == (0.0,) * 5 and plain._edge_mm == 0.0


def test_the_verdict_says_where_the_bound_was_raised_and_nothing_when_it_was_not():
    from dm2.report.summary import model_findings, verdict

    def lay(layer, **raised):
        return {"layer": layer, "statistics": {
            "uncertainty_inflation": {**dict.fromkeys(FACTORS, 1.0), **raised}}}

    quiet = {"layers": [lay(0), lay(1, plume_convex=1.3)], "tracks": []}
    assert model_findings(quiet) == []
    assert verdict(quiet)["sentences"] == []
    loud = {"layers": [lay(0), lay(1, plume_convex=1.6), lay(2, plume_convex=2.61, wall=1.2)],
            "tracks": []}
    assert model_findings(loud) == [
        "the deposit departs from the model where the part is convex (edges, ridges): its "
        "bound raised up to 2.6x from layer 1"]
    v = verdict(loud)
    assert v["sentences"] == [f"Model finding: {model_findings(loud)[0]}."]
    assert v["headline"].startswith("No defect found in 3 layers")
    assert model_findings({"layers": [{"layer": 0, "statistics": {}}]}) == []  # older reports
