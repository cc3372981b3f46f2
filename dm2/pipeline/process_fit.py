"""The reference follows the real process: a bounded, rate-limited fit of the deposition scale.

It reads each analysed layer's deviation (:mod:`dm2.defects`) and sets the scale the near-net
reference (:mod:`dm2.reference`) deposits with from the next layer on, so it is a pipeline step
between the two, not part of either.

The near-net reference uses the nominal process. A cell whose powder deposits a few per cent
less (or more) than nominal builds a part that drifts away from it everywhere, which the paper's
rule would call one huge under/overbuild. After every analysed layer this fit compares the
measured and reference heights on the part's well observed top (vertices inside the planned
outline, ``|n_z| >= TOP_NZ``, not unobserved) and estimates the process scale ``s_hat`` (the
product of efficiency and feed against nominal): the measured growth since the first layer
over the growth the reference would have had at the nominal process. The first layer, sprayed
onto the bare plate, is left out: on every twin run, whatever its process, it grew 11-15 %
less than the model (a model error of that layer, not a process offset; absorbing it lowered
the reference of every later layer and widened every overbuild). The scale the reference
deposits with from the next layer on moves towards ``s_hat`` by at most ``rate_per_layer``
per layer and stays within ``1 +- bound``. So a slow systematic offset is absorbed over a few
layers, and a fault faster or larger than that (an efficiency drift of 30 %/layer, a feed
step of 60 %) is still measured as a defect; the plume sigma is not fitted.

What the fit absorbs is never hidden: every layer's height ratio (measured over nominal top
height), estimate and applied scale are in report.json (``process``), and an estimate
``finding_threshold`` or more off nominal is a *process finding*, e.g. "deposition efficiency
8 % below nominal since layer 3; at this rate the part ends 0.8 mm short".
"""

from __future__ import annotations

import numpy as np

from dm2.defects.classify import UNOBSERVED

TOP_NZ = 0.95  # |n_z| of a vertex counted as the part's top
MIN_TOP_VERTICES = 50  # fewer top vertices: no estimate this layer
MIN_HEIGHT_MM = 0.2  # reference thinner than this on the top: no estimate


class ProcessFit:
    """Per-layer estimate of the deposition scale, and the scale the reference applies.

    Parameters
    ----------
    rate_per_layer : most the applied scale moves per layer (fraction of nominal)
    bound : the applied scale stays within ``1 +- bound``
    finding_threshold : an applied scale this far off nominal is a process finding
    planned_height_mm : planned part height [mm] (for the shortfall in the finding), or None
    """

    def __init__(self, rate_per_layer: float = 0.02, bound: float = 0.10,
                 finding_threshold: float = 0.05, planned_height_mm: float | None = None):
        if not (0 <= rate_per_layer and 0 <= bound < 1 and finding_threshold > 0):
            raise ValueError(f"ProcessFit: bad rate {rate_per_layer}, bound {bound} or "
                             f"threshold {finding_threshold}")
        self.rate_per_layer = float(rate_per_layer)
        self.bound = float(bound)
        self.finding_threshold = float(finding_threshold)
        self.planned_height_mm = planned_height_mm
        self.scale = 1.0  # applied from the next layer on
        self.layers: list[dict] = []
        self._nominal_mm = 0.0  # reference top height at the nominal process (estimate)
        self._last_ref_mm = 0.0
        self._first: tuple[float, float] | None = None  # (measured, nominal) after layer one

    def update(self, result) -> float:
        """Take one analysed layer (dm2.defects.layer_analysis.LayerResult); returns the scale
        the reference applies from now on."""
        dev = result.deviation
        normals = _normals_z(dev)
        top = (dev.class_code != UNOBSERVED) & (normals >= TOP_NZ)
        if dev.outside_mm is not None:
            top &= dev.outside_mm <= 0.0
        entry = {"layer": int(result.layer), "applied_scale": self.scale, "estimate": None,
                 "top_vertices": int(top.sum())}
        if top.sum() >= MIN_TOP_VERTICES:
            meas = float(np.median(dev.vertices_O[top, 2]))
            ref = float(np.median(dev.foot_O[top, 2]))
            if ref >= MIN_HEIGHT_MM:
                # the reference's growth since the last layer was deposited at self.scale
                self._nominal_mm += max(ref - self._last_ref_mm, 0.0) / self.scale
                self._last_ref_mm = ref
                entry.update({"measured_top_mm": meas, "reference_top_mm": ref,
                              "nominal_top_mm": self._nominal_mm})
                entry["height_ratio"] = meas / max(self._nominal_mm, 1e-9)
                # the process estimate: growth since the first layer
                if self._first is None:
                    self._first = (meas, self._nominal_mm)
                elif self._nominal_mm - self._first[1] >= MIN_HEIGHT_MM:
                    est = (meas - self._first[0]) / (self._nominal_mm - self._first[1])
                    step = float(np.clip(est - self.scale, -self.rate_per_layer,
                                         self.rate_per_layer))
                    self.scale = float(np.clip(self.scale + step, 1 - self.bound,
                                               1 + self.bound))
                    entry["estimate"] = est
        entry["next_scale"] = self.scale
        self.layers.append(entry)
        return self.scale

    def findings(self) -> list[str]:
        """Process findings: the latest estimate off nominal by ``finding_threshold`` or more,
        since the first layer of the run of estimates beyond it with the same sign."""
        est = [e for e in self.layers if e["estimate"] is not None]
        if not est or abs(est[-1]["estimate"] - 1.0) < self.finding_threshold:
            return []
        s_hat = float(est[-1]["estimate"])
        sign = np.sign(s_hat - 1.0)
        since = est[-1]["layer"]
        for e in reversed(self.layers):
            if e["estimate"] is None or np.sign(e["estimate"] - 1.0) != sign or \
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
        return [text]

    def summary(self) -> dict:
        """The report.json ``process`` section."""
        return {"fitted": "deposition scale (efficiency x feed against nominal)",
                "rate_per_layer": self.rate_per_layer, "bound": self.bound,
                "scale": self.scale, "layers": self.layers, "findings": self.findings()}


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
