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
  nominal), within ``1 +- bound``, read where the plume width does not move the reference when
  enough of the top is such (:func:`~.process_top.plume_insensitive`); the plume width is the
  least-squares factor that explains the layer's edges at that scale
  (:func:`~.process_top.plume_factor`), within ``1 +- PLUME_BOUND``. A top with no such place (a
  thin wall) is lowered by a wider plume as by a lower efficiency: there the plume width is fitted
  together with a scale on the edges and the top (:func:`~.process_top.joint_plume_factor`), and
  the top's scale is read under that plume (:func:`~.process_top.joint_scale_plume`). The
  calibration is read again on the top the profilers see once the next layer has begun
  (:meth:`ProcessFit.recalibrate`): the plume width is fitted again at that scale, or, on a top
  the plume shapes, stays the one fitted together with the layer's own scale. The reference
  deposited so far is scaled and blurred by them and deposits with them from then on. A fault
  spanning the whole build from its first layer at one rate cannot be told from such an
  offset; it is reported as a process finding, not hidden.
* **Later layers: a slow follower.** The estimate ``s_hat`` is the measured growth since the
  calibration layer over the growth the reference would have had at the nominal process, read on the
  layer's own top vertices against the calibration layer at the same places
  (:class:`dm2.process.calibration_top.CalibrationTop`), on those where the plume width does not
  matter when enough are (:func:`~.process_top.plume_insensitive`). Where too few of them lie on the
  calibration layer's top it is read as the two layers' top heights. The scale moves towards it by
  at most ``rate_per_layer`` per layer (from then on only; what was deposited stays as it was) and
  stays within ``1 +- bound``. So a slow drift is absorbed over many layers and still reported, and
  a fault faster or larger than that (an efficiency drift of 25 %/layer, a feed step of 40 %) is
  measured as a defect. The plume width is not followed after the calibration.

What the fit absorbs is never hidden: every layer's height ratio (measured over nominal top
height), estimate, applied scale and the calibrated plume factor are in report.json
(``process``), and the findings (:meth:`ProcessFit.finding_details`: an *offset* off nominal or
a *change* off the calibration) are in the verdict, e.g. "deposition efficiency 8 % below
nominal since layer 0; at this rate the part ends 0.8 mm short".
"""

from __future__ import annotations

import numpy as np

from dm2.defects.classify import DEFECT_CLASSES, UNOBSERVED
from dm2.process.calibration_top import CalibrationTop
from dm2.process.process_top import (
    MIN_HEIGHT_MM,
    MIN_TOP_VERTICES,
    PLUME_DOUBT,
    TOP_NZ,
    joint_scale_plume,
    normals_z,
    not_stale,
    on_plateau,
    plume_factor,
    plume_insensitive,
    plume_lift,
    plume_share,
    scale_under_plume,
    top_heights,
)

CHANGE_FACTOR = 2.0  # a change of the process: twice the finding threshold off the calibration
PLUME_BOUND = 0.25  # the calibrated plume width stays within 1 +- this of nominal


def process_fit_on(monitor_cfg) -> bool:
    """``[monitor] process_fit``, by default on with the executed reference clock only."""
    if monitor_cfg.process_fit is None:
        return monitor_cfg.reference_clock == "executed"
    return bool(monitor_cfg.process_fit)


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
        self.plume_bound = PLUME_BOUND
        self.scale = 1.0  # the reference deposits at this scale (from the next state on)
        self.layers: list[dict] = []
        self._nominal_mm = 0.0  # reference top height at the nominal process (estimate)
        self._last_ref_mm = 0.0  # the reference's top after the last update (as rescaled)
        self._first: tuple[float, float] | None = None  # (measured, nominal) at calibration
        self._calibration: dict | None = None  # the calibration layer until recalibrate()
        self._top: CalibrationTop | None = None  # the calibration layer's top, for the growth
        self._grown_mm = 0.0  # the reference's top growth since the calibration (as applied)

    def _growth_estimate(self, xy_O, z_mm, seen_mm, area, entry: dict) -> float | None:
        """The scale the part grew at since the calibration layer, read at the later layer's
        own top vertices (:class:`CalibrationTop`): their measured over their reference growth,
        times the growth-weighted scale the reference deposited that growth at; None when too
        few of them lie where the calibration layer's top was, or it grew too little."""
        if self._top is None:
            return None
        ratio, ref_growth, n = self._top.growth_ratio(xy_O, z_mm, seen_mm, area,
                                                      MIN_TOP_VERTICES)
        entry["growth_vertices"] = n
        nominal = self._nominal_mm - self._first[1]
        if ratio is None or ref_growth < MIN_HEIGHT_MM or self._grown_mm <= 0.0:
            return None
        return ratio * self._grown_mm / nominal  # the reference grew at that mean scale

    def update(self, result) -> tuple[float, float, float]:
        """Take one analysed layer (dm2.defects.layer_analysis.LayerResult).

        Returns ``(scale, rescale, plume)``: the scale the reference deposits with from now
        on, the factor by which the reference deposited so far is to be scaled, and the factor
        its plume width is to be widened by (both 1 except at the calibration layer)."""
        dev = result.deviation
        reference = getattr(result, "reference", None)
        normals = normals_z(dev)
        top = (dev.class_code != UNOBSERVED) & (normals >= TOP_NZ)
        top &= ~np.isin(dev.class_code, DEFECT_CLASSES)  # the process where no defect is
        top &= not_stale(dev)
        if dev.outside_mm is not None:
            top &= dev.outside_mm <= 0.0
        top &= on_plateau(reference, dev.foot_O, top)
        entry = {"layer": int(result.layer), "applied_scale": self.scale, "estimate": None,
                 "top_vertices": int(top.sum())}
        rescale = plume = 1.0
        if top.sum() >= MIN_TOP_VERTICES:
            seen_ref = dev.foot_O[top, 2]  # the reference as the profilers last saw it
            if getattr(dev, "unseen_mm", None) is not None:
                seen_ref = seen_ref - dev.unseen_mm[top]
            area = getattr(dev, "vertex_area_mm2", None)
            area = np.ones(seen_ref.size) if area is None else np.asarray(area)[top]
            xy_top, z_top = dev.foot_O[top, :2], dev.vertices_O[top, 2]
            ref, meas = top_heights(seen_ref, z_top, area)
            if ref >= MIN_HEIGHT_MM:
                # the reference's growth since the last update was deposited at self.scale
                grown = max(ref - self._last_ref_mm, 0.0)
                self._nominal_mm += grown / self.scale
                self._grown_mm += grown
                self._last_ref_mm = ref
                entry.update({"measured_top_mm": meas, "reference_top_mm": ref,
                              "nominal_top_mm": self._nominal_mm})
                entry["height_ratio"] = meas / max(self._nominal_mm, 1e-9)
                if self._first is None:  # calibration: the process so far
                    est = entry["height_ratio"]
                    flat = plume_insensitive(reference, xy_top, MIN_TOP_VERTICES)
                    if flat is not None:  # read where the plume width does not matter
                        ref_flat, meas_flat = top_heights(seen_ref[flat], z_top[flat],
                                                           area[flat])
                        est = meas_flat / ref_flat * self.scale
                    entry["plateau"] = flat is not None
                    lift = 0.0
                    if flat is None:  # the plume shapes this top: what it may move, reported
                        entry["plume_share"] = plume_share(reference, xy_top, area, ref)
                        lift = entry["plume_lift"] = plume_lift(reference, xy_top, area, ref)
                    self._first = (meas, self._nominal_mm)
                    self._grown_mm = 0.0
                    new, plume = joint_scale_plume(result, est, lift, self.bound,
                                                   self.plume_bound)
                    rescale = new / self.scale
                    self._calibration = {"result": result, "ref": ref, "entry": entry,
                                         "scale": self.scale}
                    self._last_ref_mm = ref * rescale
                    entry["calibration"] = True
                    entry["plume_factor"] = plume
                    if reference is not None:
                        self._top = CalibrationTop(reference, self.scale, xy_top, z_top,
                                                   seen_ref)
                        self._top.calibrate(new, plume)
                elif self._nominal_mm - self._first[1] >= MIN_HEIGHT_MM:
                    flat = plume_insensitive(reference, xy_top, MIN_TOP_VERTICES)
                    flat = np.ones(len(xy_top), bool) if flat is None else flat
                    est = self._growth_estimate(xy_top[flat], z_top[flat], seen_ref[flat],
                                                area[flat], entry)
                    if est is None:  # too little of the top where the calibration's was
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
        return self.scale, rescale, plume

    @property
    def calibrating(self) -> bool:
        """No layer has calibrated the scale yet."""
        return self._first is None

    def recalibrate(self, top) -> tuple[float, float, float] | None:
        """The calibration again from the calibration layer's top as the profilers saw it
        once the next layer had begun (:class:`dm2.process.reobserved_top.ReobservedTop`),
        when enough of it was seen: the ``(scale, rescale, plume)`` to apply instead of the
        layer's own, or None to keep those. Later estimates still measure the growth since
        the fused calibration layer, whose lag then cancels."""
        cal, self._calibration = self._calibration, None
        if cal is None:
            return None
        dev = cal["result"].deviation
        defects = dev.vertices_O[np.isin(dev.class_code, DEFECT_CLASSES), :2]
        fused = None if self._top is None else (self._top.xy_O, self._top.z_mm)
        ratio, cells = top.estimate(defects, fused)
        entry = cal["entry"]
        entry["reobserved_cells"] = cells
        if ratio is None:
            return None
        est = ratio * cal["scale"]  # the reference was deposited at cal["scale"] so far
        lift = entry.get("plume_lift", 0.0)
        if lift == 0.0:  # the scale read apart from the plume: the plume fitted at it
            new = scale_under_plume(est, 1.0, 0.0, self.bound)
            plume = plume_factor(cal["result"], new, self.plume_bound)
        else:  # the plume fitted with the layer's own scale; the scale read under it
            plume = entry["plume_factor"]
            new = scale_under_plume(est, plume, lift, self.bound)
        rescale = new / cal["scale"]
        self._last_ref_mm = cal["ref"] * rescale
        if self._top is not None:
            self._top.calibrate(new, plume)
        entry.update({"fused_estimate": entry["estimate"], "estimate": est,
                      "plume_factor": plume, "next_scale": new})
        self.scale = new
        return new, rescale, plume

    def finding_details(self) -> list[dict]:
        """The process findings as data, each ``{"kind", "quantity", "estimate", "sign",
        "since_layer", "text"}``:

        * ``change``: the latest estimate off the calibrated scale by ``CHANGE_FACTOR *
          finding_threshold`` or more of it (the calibration itself is good to about +-5 % on the
          twin's parts), since the first layer of the trailing run of such estimates with its
          sign: a drift or step of the process during the build;
        * ``offset``: without a change, the cell's scale off nominal by ``finding_threshold``
          or more, since the calibration layer. The scale is the calibration's where it was
          read on a plateau (``plateau``: where the plume width does not move the reference):
          the first layer's whole top (1,000-4,000 vertices on the regression parts, within
          1.2 % of the twin's scale), where later layers read their growth on a shrinking top
          near the edges (60-700 vertices, up to 3 % off on the same runs). Without a plateau
          (a thin wall, a 10 mm bar) the scale is read together with the plume width, which
          moves the top as much as the deposition does; such an offset also states
          (``plume_doubt``, in the text too) how far a plume ``PLUME_DOUBT`` off the fitted
          one moves the scale read on that top (:func:`~.process_top.plume_share`).
        """
        cal = next((e for e in self.layers if e.get("calibration")), None)
        if cal is None:
            return []
        s0 = float(cal["next_scale"])
        later = [e for e in self.layers if e["estimate"] is not None and e is not cal]
        out = []
        # the cell's scale, while nothing changed (see the docstring)
        base = s0
        change = CHANGE_FACTOR * self.finding_threshold
        if later and abs(later[-1]["estimate"] / s0 - 1.0) >= change:
            s_hat = float(later[-1]["estimate"])
            sign = int(np.sign(s_hat - s0))
            since = later[-1]["layer"]
            for e in reversed(later):
                if np.sign(e["estimate"] - s0) != sign or abs(e["estimate"] / s0 - 1.0) < change:
                    break
                since = e["layer"]
            base = None  # a drift's start blurs into the estimates before it: no offset then
            pct = abs(s_hat / s0 - 1.0) * 100
            text = (f"deposition {'fell' if sign < 0 else 'rose'} {pct:.0f} % against the "
                    f"first layer since layer {since}")
            if self.planned_height_mm:
                short = (1.0 - s_hat / s0) * self.planned_height_mm
                text += (f"; at this rate the part ends {abs(short):.1f} mm "
                         f"{'short' if short > 0 else 'too tall'}")
            out.append({"kind": "change", "quantity": "deposition scale", "estimate": s_hat,
                        "sign": sign, "since_layer": int(since), "text": text})
        if base is not None and abs(base - 1.0) >= self.finding_threshold:
            sign = int(np.sign(base - 1.0))
            pct = abs(base - 1.0) * 100
            text = (f"deposition efficiency {pct:.0f} % {'below' if sign < 0 else 'above'} "
                    f"nominal since layer {cal['layer']}")
            doubt = None
            if cal.get("plume_share") is not None:  # read on a top the plume width shapes
                doubt = PLUME_DOUBT * float(cal["plume_share"]) * float(base)
                text += (f" (read with the plume width on a top it shapes: a plume "
                         f"{PLUME_DOUBT * 100:.0f} % wider or narrower than fitted moves "
                         f"this by {doubt * 100:.0f} %)")
            if self.planned_height_mm:
                short = (1.0 - base) * self.planned_height_mm
                text += (f"; at this rate the part ends {abs(short):.1f} mm "
                         f"{'short' if short > 0 else 'too tall'}")
            out.insert(0, {"kind": "offset", "quantity": "deposition scale",
                           "estimate": float(base), "sign": sign,
                           "since_layer": int(cal["layer"]), "text": text,
                           "plume_doubt": doubt})
        return out

    def findings(self) -> list[str]:
        """The process findings' sentences (:meth:`finding_details`)."""
        return [f["text"] for f in self.finding_details()]

    def summary(self) -> dict:
        """The report.json ``process`` section."""
        return {"fitted": "deposition scale (efficiency x feed against nominal); plume width "
                          "at the calibration",
                "calibration": "first layer", "rate_per_layer": self.rate_per_layer,
                "bound": self.bound, "scale": self.scale, "layers": self.layers,
                "findings": self.findings(), "finding_details": self.finding_details()}
