"""The twin's check of its own truth: is the true surface one a cold-spray cell could grow?

A run's truth is only worth scoring against when the deposit it holds is physical. Three
checks on the final true surface and the run's bookkeeping (``truth/validity.json``):

* **steepest slope over the plume's width**: the height difference across ``2 sigma``
  (the plume's standard deviation either side of each node), as an angle from level. A face
  steeper than the critical angle over a whole plume width is one the jet cannot build (what
  strikes it rebounds), so the surface holding it is not a sprayed one.
* **narrow features**: what stands above the surface's grey opening with a cone of diameter
  ``sigma`` whose flanks slope at the critical angle (a feature narrower than the plume's
  sigma and steeper than a jet can build), against one layer height. A plume about
  ``2 sigma`` wide cannot grow such a spike a layer above its surroundings, while a sprayed
  cone's tip (flanks below the critical angle) is kept; the twin's old needles stood 30 mm
  above theirs.
* **mass balance**: the volume the height field gained by deposition (blobs of injected bumps
  and dents taken out) against the volume the packets that stuck carried, and the powder the
  spray model drew against ``feed x time`` of the executed motion (its planned packet
  counts), each within ``MASS_BALANCE_TOLERANCE``; the overall deposition efficiency (stuck
  over fed) is reported beside them.

The planned and true tops are reported too (the part's top against the toolpath's), as
information: a part that stands short of plan is physical (cold-spray parts taper) but is
worth knowing about.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

MASS_BALANCE_TOLERANCE = 0.01  # relative, each of the two volume balances


def steepest_slope_deg(H: np.ndarray, cell_mm: float, span_mm: float) -> float:
    """Steepest slope [deg from level] of ``H`` over ``2 span_mm`` (central differences
    ``span_mm`` either side of each node, combined over x and y)."""
    k = max(1, int(round(span_mm / cell_mm)))
    if min(H.shape) <= 2 * k:
        return 0.0
    gx = np.zeros_like(H)
    gy = np.zeros_like(H)
    gx[:, k:-k] = (H[:, 2 * k:] - H[:, :-2 * k]) / (2 * k * cell_mm)
    gy[k:-k, :] = (H[2 * k:, :] - H[:-2 * k, :]) / (2 * k * cell_mm)
    return float(np.degrees(np.arctan(np.sqrt(gx * gx + gy * gy).max())))


def narrow_features(H: np.ndarray, cell_mm: float, width_mm: float,
                    max_slope_deg: float) -> tuple[float, float]:
    """The highest rise [mm] of a feature narrower than ``width_mm`` above its neighbourhood,
    and the area [mm^2] that rises more than half that.

    The neighbourhood is ``H``'s grey opening with a cone of that diameter whose flanks slope
    at ``max_slope_deg``: it keeps every crest and apex whose flanks are no steeper (a sprayed
    cone's tip, a wall's crest), and cuts what rises steeper than that within the width (a
    needle), so what stands above it is a feature no jet could have built."""
    r = max(1, int(round(0.5 * width_mm / cell_mm)))
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    d = np.hypot(xx, yy)
    disc = d <= r
    cone = -math.tan(math.radians(max_slope_deg)) * cell_mm * d
    opened = ndimage.grey_opening(H, footprint=disc, structure=np.where(disc, cone, 0.0),
                                  mode="nearest")
    rise = H - opened
    top = float(rise.max()) if rise.size else 0.0
    area = float(np.count_nonzero(rise > 0.5 * top)) * cell_mm * cell_mm if top > 0 else 0.0
    return top, area


def check_truth(H: np.ndarray, cell_mm: float, *, sigma_mm: float, layer_mm: float,
                critical_angle_deg: float, field_gain_mm3: float, stuck_mm3: float,
                fed_mm3: float, planned_fed_mm3: float,
                planned_top_mm: float | None = None) -> dict:
    """The validity of a twin run's truth (see the module's checks).

    Parameters
    ----------
    H : (ny, nx) final true heights [mm] in O
    cell_mm : node spacing [mm]
    sigma_mm : the plume's standard deviation at the nominal standoff [mm]
    layer_mm : the toolpath's layer height [mm]
    critical_angle_deg : the spray's critical angle [deg]
    field_gain_mm3 : volume the field gained by deposition [mm^3]
    stuck_mm3 : volume the stuck packets carried (the spray model's count) [mm^3]
    fed_mm3, planned_fed_mm3 : powder volume drawn, and ``feed x time`` of the motion [mm^3]
    planned_top_mm : the planned part's top over the layers run [mm]

    Returns
    -------
    dict: ``valid`` and ``reasons`` (one line per failed check), then each check's figures.
    """
    slope = steepest_slope_deg(H, cell_mm, sigma_mm)
    rise, rise_area = narrow_features(H, cell_mm, sigma_mm, critical_angle_deg)
    gain_err = abs(field_gain_mm3 - stuck_mm3) / stuck_mm3 if stuck_mm3 > 0 else 0.0
    fed_err = (abs(fed_mm3 - planned_fed_mm3) / planned_fed_mm3 if planned_fed_mm3 > 0
               else 0.0)
    reasons = []
    if slope > critical_angle_deg:
        reasons.append(f"steepest slope over the plume's width {slope:.1f} deg exceeds the "
                       f"critical angle {critical_angle_deg:.1f} deg")
    if rise > layer_mm:
        reasons.append(f"a feature narrower than the plume's sigma ({sigma_mm:.2f} mm) stands "
                       f"{rise:.2f} mm above its neighbourhood (more than a layer, "
                       f"{layer_mm:.2f} mm)")
    if gain_err > MASS_BALANCE_TOLERANCE:
        reasons.append(f"the field gained {field_gain_mm3:.1f} mm3 against {stuck_mm3:.1f} mm3 "
                       f"stuck ({100 * gain_err:.2f} % off)")
    if fed_err > MASS_BALANCE_TOLERANCE:
        reasons.append(f"the spray drew {fed_mm3:.1f} mm3 of powder against {planned_fed_mm3:.1f}"
                       f" mm3 of feed x time ({100 * fed_err:.2f} % off)")
    true_top = float(H.max()) if H.size else 0.0
    return {
        "valid": not reasons, "reasons": reasons,
        "steepest_slope_deg": slope, "slope_limit_deg": float(critical_angle_deg),
        "slope_span_mm": 2.0 * sigma_mm,
        "narrow_feature_rise_mm": rise, "narrow_feature_area_mm2": rise_area,
        "narrow_feature_width_mm": sigma_mm, "narrow_feature_limit_mm": layer_mm,
        "field_gain_mm3": field_gain_mm3, "stuck_mm3": stuck_mm3,
        "field_vs_stuck_error": gain_err, "fed_mm3": fed_mm3,
        "planned_fed_mm3": planned_fed_mm3, "fed_vs_plan_error": fed_err,
        "efficiency": stuck_mm3 / fed_mm3 if fed_mm3 > 0 else None,
        "mass_balance_tolerance": MASS_BALANCE_TOLERANCE,
        "true_top_mm": true_top, "planned_top_mm": planned_top_mm,
        "top_vs_plan": (true_top / planned_top_mm - 1.0 if planned_top_mm else None),
    }
