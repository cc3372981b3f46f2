"""The reference follows the real process: the first layer calibrates the deposition scale,
and a bounded, rate-limited fit follows it from there.

It reads each analysed layer's deviation (:mod:`dm2.defects`) and sets the scale the near-net
reference (:mod:`dm2.reference`) deposits with, so it is a pipeline step between the two, not
part of either.

The near-net reference uses the nominal process. A cell whose powder deposits a few per cent
less (or more) than nominal builds a part that drifts away from it everywhere, which the paper's
rule would call one huge under/overbuild. Deposition efficiencies of nominally equal cold-spray
runs scatter by 10-20 % (powder lot, gas temperature, nozzle wear), so the nominal rate alone
cannot be the yardstick. The fit compares the measured and reference heights on the part's well
observed top (vertices inside the planned outline, ``|n_z| >= TOP_NZ``, not unobserved):

* **First layer: calibration.** The ratio of the measured to the reference top height after the
  first layer with enough top is the cell's deposition scale ``s_0`` (efficiency x feed against
  nominal), within ``1 +- bound``. The reference deposited so far is scaled by it and deposits
  at it from then on. A fault spanning the whole build from its first layer at one rate cannot
  be told from such an offset; it is reported as a process finding, not hidden.
* **Later layers: a slow follower.** The estimate ``s_hat`` is the measured growth since the
  calibration layer over the growth the reference would have had at the nominal process. The
  scale moves towards it by at most ``rate_per_layer`` per layer (from then on only; what was
  deposited stays as it was) and stays within ``1 +- bound``. So a slow drift is absorbed over
  many layers and still reported, and a fault faster or larger than that (an efficiency drift of
  25 %/layer, a feed step of 40 %) is measured as a defect. The plume sigma is not fitted.

What the fit absorbs is never hidden: every layer's height ratio (measured over nominal top
height), estimate and applied scale are in report.json (``process``), and an estimate
``finding_threshold`` or more off nominal is a *process finding*, e.g. "deposition efficiency
8 % below nominal since layer 0; at this rate the part ends 0.8 mm short"
(``finding_details`` gives its scale, sign and first layer).
"""

from __future__ import annotations

import numpy as np

from dm2.defects.classify import UNOBSERVED

TOP_NZ = 0.95  # |n_z| of a vertex counted as the part's top
MIN_TOP_VERTICES = 50  # fewer top vertices: no estimate this layer
MIN_HEIGHT_MM = 0.2  # reference thinner than this on the top: no estimate
PLATEAU_SLOPE = 0.1  # reference slope [mm/mm] of the plateau the scale is measured on
PLATEAU_FRACTION = 0.7  # of the top's 95th-percentile reference height


class ProcessFit:
    """Deposition scale: calibrated on the first layer, then followed slowly (module docstring).

    Parameters
    ----------
    rate_per_layer : most the applied scale moves per layer after the calibration layer
    bound : the applied scale stays within ``1 +- bound``
    finding_threshold : an estimate this far off nominal is a process finding
    planned_height_mm : planned part height [mm] (for the shortfall in the finding), or None
    """

    def __init__(self, rate_per_layer: float = 0.02, bound: float = 0.25,
                 finding_threshold: float = 0.05, planned_height_mm: float | None = None):
        if not (0 <= rate_per_layer and 0 <= bound < 1 and finding_threshold > 0):
            raise ValueError(f"ProcessFit: bad rate {rate_per_layer}, bound {bound} or "
                             f"threshold {finding_threshold}")
        self.rate_per_layer = float(rate_per_layer)
        self.bound = float(bound)
        self.finding_threshold = float(finding_threshold)
        self.planned_height_mm = planned_height_mm
        self.scale = 1.0  # the reference deposits at this scale (from the next state on)
        self.layers: list[dict] = []
        self._nominal_mm = 0.0  # reference top height at the nominal process (estimate)
        self._last_ref_mm = 0.0  # the reference's top after the last update (as rescaled)
        self._first: tuple[float, float] | None = None  # (measured, nominal) at calibration

    def update(self, result) -> tuple[float, float]:
        """Take one analysed layer (dm2.defects.layer_analysis.LayerResult).

        Returns ``(scale, rescale)``: the scale the reference deposits with from now on, and
        the factor by which the reference deposited so far is to be scaled (1 except at the
        calibration layer)."""
        dev = result.deviation
        normals = _normals_z(dev)
        top = (dev.class_code != UNOBSERVED) & (normals >= TOP_NZ)
        if dev.outside_mm is not None:
            top &= dev.outside_mm <= 0.0
        top &= _on_plateau(getattr(result, "reference", None), dev.foot_O, top)
        entry = {"layer": int(result.layer), "applied_scale": self.scale, "estimate": None,
                 "top_vertices": int(top.sum())}
        rescale = 1.0
        if top.sum() >= MIN_TOP_VERTICES:
            meas = float(np.median(dev.vertices_O[top, 2]))
            seen_ref = dev.foot_O[top, 2]  # the reference as the profilers last saw it
            if getattr(dev, "unseen_mm", None) is not None:
                seen_ref = seen_ref - dev.unseen_mm[top]
            ref = float(np.median(seen_ref))
            if ref >= MIN_HEIGHT_MM:
                # the reference's growth since the last update was deposited at self.scale
                self._nominal_mm += max(ref - self._last_ref_mm, 0.0) / self.scale
                self._last_ref_mm = ref
                entry.update({"measured_top_mm": meas, "reference_top_mm": ref,
                              "nominal_top_mm": self._nominal_mm})
                entry["height_ratio"] = meas / max(self._nominal_mm, 1e-9)
                if self._first is None:  # calibration: the process so far
                    est = entry["height_ratio"]
                    self._first = (meas, self._nominal_mm)
                    new = float(np.clip(est, 1 - self.bound, 1 + self.bound))
                    rescale = new / self.scale
                    self._last_ref_mm = ref * rescale
                    entry["calibration"] = True
                elif self._nominal_mm - self._first[1] >= MIN_HEIGHT_MM:
                    est = (meas - self._first[0]) / (self._nominal_mm - self._first[1])
                    step = float(np.clip(est - self.scale, -self.rate_per_layer,
                                         self.rate_per_layer))
                    new = float(np.clip(self.scale + step, 1 - self.bound, 1 + self.bound))
                else:
                    est, new = None, self.scale
                self.scale = new
                entry["estimate"] = est
        entry["next_scale"] = self.scale
        self.layers.append(entry)
        return self.scale, rescale

    def finding_details(self) -> list[dict]:
        """The process findings as data: ``{"quantity", "estimate", "sign", "since_layer",
        "text"}``; the latest estimate off nominal by ``finding_threshold`` or more, since the
        first layer of the run of estimates beyond it with the same sign."""
        est = [e for e in self.layers if e["estimate"] is not None]
        if not est or abs(est[-1]["estimate"] - 1.0) < self.finding_threshold:
            return []
        s_hat = float(est[-1]["estimate"])
        sign = int(np.sign(s_hat - 1.0))
        since = est[-1]["layer"]
        for e in reversed(self.layers):
            if e["estimate"] is None:
                continue
            if np.sign(e["estimate"] - 1.0) != sign or \
                    abs(e["estimate"] - 1.0) < self.finding_threshold:
                break
            since = e["layer"]
        pct = abs(s_hat - 1.0) * 100
        text = (f"deposition efficiency {pct:.0f} % {'below' if sign < 0 else 'above'} "
                f"nominal since layer {since}")
        if self.planned_height_mm:
            short = (1.0 - s_hat) * self.planned_height_mm
            text += (f"; at this rate the part ends {abs(short):.1f} mm "
                     f"{'short' if short > 0 else 'tall'}")
        return [{"quantity": "deposition scale", "estimate": s_hat, "sign": sign,
                 "since_layer": int(since), "text": text}]

    def findings(self) -> list[str]:
        """The process findings' sentences (:meth:`finding_details`)."""
        return [f["text"] for f in self.finding_details()]

    def summary(self) -> dict:
        """The report.json ``process`` section."""
        return {"fitted": "deposition scale (efficiency x feed against nominal)",
                "calibration": "first layer", "rate_per_layer": self.rate_per_layer,
                "bound": self.bound, "scale": self.scale, "layers": self.layers,
                "findings": self.findings(), "finding_details": self.finding_details()}


def _on_plateau(reference, foot_O, top) -> np.ndarray:
    """Vertices whose reference is on the part's plateau: slope at most ``PLATEAU_SLOPE`` and
    at least ``PLATEAU_FRACTION`` of the top's 95th-percentile height. The edges' ramps are
    left out: there the plume width decides the height (a plume a few per cent wider than
    modelled lowers them), not the deposition scale."""
    if reference is None or not np.any(top):
        return np.ones(top.shape, bool)
    h = foot_O[:, 2]
    slope = np.linalg.norm(reference.gradient_at(foot_O[:, :2]), axis=-1)
    return (slope <= PLATEAU_SLOPE) & (h >= PLATEAU_FRACTION * np.percentile(h[top], 95))


def _normals_z(dev) -> np.ndarray:
    """|n_z| (n,) of the layer mesh's vertex normals."""
    from dm2.defects.classify import curvature_and_areas

    if dev.normals_O is not None:
        return np.abs(dev.normals_O[:, 2])
    if dev.n_vertices == 0:
        return np.zeros(0)
    _, _, normals = curvature_and_areas(dev.vertices_O, dev.faces, return_normals=True,
                                        smooth_iterations=0)
    return np.abs(normals[:, 2])
