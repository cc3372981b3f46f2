"""The model-error terms of the uncertainty, set to what the layer itself shows.

The uncertainty model's coefficients (:mod:`dm2.defects.uncertainty`) are fitted once, on a
cell whose physics is close to the monitor's model. Another cell's deposition departs from the
Gaussian model in its own way: an efficiency that falls faster with the impact angle, a plume
of another shape. That error is *systematic* and lives where the model is weakest: on walls,
edges, ramps and wall feet, all around the part. A defect is *local*: it covers a small part of
those places. So each layer measures, for each model-error term, how large the deviations are
where that term dominates the predicted variance:

* the term's **bin** is every observed vertex where the term holds more than ``TERM_SHARE`` of
  the predicted variance; a bin of fewer than ``MIN_BIN_VERTICES`` vertices says nothing;
* the bin's **robust RMS** of ``z = d / sigma`` is ``sqrt(median(z^2) / median(chi2_1))``: 1
  where the model predicts the spread, larger where this cell's model error is larger (its bias
  included). The median ignores the bin's minority, so a defect on part of the walls or edges
  does not raise its own bound;
* the term's standard deviation is multiplied by that RMS, within ``MIN_FACTOR`` and
  ``MAX_INFLATION``. Raised, it absorbs a cell that errs more than the one the coefficients
  were fitted on. Lowered, it follows a cell, or a deposit, closer to the model than that one:
  the fitted model-error terms are a conservative fit, and where the layer's own deviations
  stay far inside them they would hide a defect there (the default run's corner overbuild,
  measured at 0.68 mm on fresh deposit at a wall, stood inside a 0.60 mm bound whose wall and
  convex plume terms that layer's walls and edges showed more than twice too wide). It is
  lowered at most to half: a bin's median says how most of it behaves, and half of a fitted
  term still covers the minority.

Only the model-shape terms (``MODEL_TERMS``) follow the layer. The floor and range terms are the
measurement's, and a uniform offset of the whole top is the process fit's business
(:mod:`dm2.process.process_fit`): raising them would hide a global over- or underbuild.
The plume term has two bins, concave and convex reference (where the plume's tail lands and
where it leaves), because a plume of another width or shape errs there by different amounts
and in opposite directions. The factors of each layer are in report.json
(``layers[].statistics.uncertainty_inflation``), so what the bound absorbed is never hidden;
the real-time columns take the last analysed layer's factors (:func:`live_factors`) where the
process fit is applied (dm2.pipeline.session; with the process fit off they keep the configured
bound).
"""

from __future__ import annotations

import numpy as np

from dm2.defects.uncertainty import FEATURES

MODEL_TERMS = ("wall", "edge", "foot", "plume")
# the plume term's bins: where the reference is concave (the plume's tail lands: wall feet, hole
# rims) and where it is convex (the tail leaves: edges, ridges); a plume of another width or
# shape errs there in opposite directions and by different amounts
FACTORS = ("wall", "edge", "foot", "plume_concave", "plume_convex")
TERM_SHARE = 0.5  # a vertex belongs to a term's bin where the term holds this share of sigma^2
MIN_BIN_VERTICES = 100  # fewer vertices in a bin: no evidence, factor 1
MAX_INFLATION = 3.0  # a term's standard deviation is raised at most this many times
MIN_FACTOR = 0.5  # and lowered at most to this share of the configured one
CHI2_1_MEDIAN = 0.45493642311957283  # median of z^2 for a standard normal z


def model_inflation(features: np.ndarray, deviation_mm: np.ndarray, coefficients: np.ndarray,
                    observed: np.ndarray, concave: np.ndarray) -> dict[str, float]:
    """Factors ``{name: MIN_FACTOR <= factor <= MAX_INFLATION}`` of :data:`FACTORS` on the
    model-error terms' standard deviations, from one layer's vertices (1 where a bin has too
    few vertices to say).

    Parameters
    ----------
    features : (n, 8) uncertainty features (dm2.defects.uncertainty.uncertainty_features)
    deviation_mm : (n,) signed deviation [mm]
    coefficients : (8,) variance coefficients [mm^2] (dm2.defects.uncertainty.coefficients)
    observed : (n,) bool, the vertices the layer observed
    concave : (n,) bool, the reference's plume sensitivity is positive there (concave)
    """
    factors = dict.fromkeys(FACTORS, 1.0)
    seen = np.asarray(observed, bool)
    if np.count_nonzero(seen) < MIN_BIN_VERTICES:
        return factors
    f = np.asarray(features, np.float64)
    c = np.asarray(coefficients, np.float64)
    var = f @ c
    ok = seen & (var > 0.0)
    d = np.asarray(deviation_mm, np.float64)
    z2 = np.divide(d * d, var, out=np.zeros(var.shape), where=ok)
    half = TERM_SHARE * var
    cc = np.asarray(concave, bool)
    for name in FACTORS:
        k = FEATURES.index(name.split("_")[0])
        in_bin = ok & (f[:, k] * c[k] > half)
        if name == "plume_concave":
            in_bin &= cc
        elif name == "plume_convex":
            in_bin &= ~cc
        if np.count_nonzero(in_bin) < MIN_BIN_VERTICES:
            continue
        rms = float(np.sqrt(np.median(z2[in_bin]) / CHI2_1_MEDIAN))
        factors[name] = min(max(rms, MIN_FACTOR), MAX_INFLATION)
    return factors


def inflated_sigma_mm(features: np.ndarray, coefficients: np.ndarray, factors: dict,
                      concave: np.ndarray) -> np.ndarray:
    """Standard deviation [mm] (n,) with the model-error terms raised by ``factors``."""
    f = np.asarray(features, np.float64)
    coef = np.array(coefficients, np.float64)
    if all(v == 1.0 for v in factors.values()):  # bit for bit dm2.defects.uncertainty's sigma
        return np.sqrt(np.maximum(f @ coef, 0.0))
    plume = FEATURES.index("plume")
    for name in ("wall", "edge", "foot"):
        coef[FEATURES.index(name)] *= factors[name] ** 2
    c_plume, coef[plume] = coef[plume], 0.0
    var = f @ coef
    if c_plume > 0.0:
        scale = np.where(np.asarray(concave, bool), factors["plume_concave"],
                         factors["plume_convex"]) ** 2
        var = var + f[:, plume] * (c_plume * scale)
    return np.sqrt(np.maximum(var, 0.0))


def live_factors(factors: dict | None) -> dict:
    """The factors the real-time columns take: their plume term does not tell concave from
    convex, so it takes the larger of the two (the cautious side: fewer alarms)."""
    if not factors:
        return {}
    return {"wall": factors["wall"], "edge": factors["edge"],
            "plume": max(factors["plume_concave"], factors["plume_convex"])}
