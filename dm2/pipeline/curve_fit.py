"""Refit the efficiency curve's falloff (``[process] efficiency_cos_exponent``) from a fault-free
recording of one's own cell.

The near-net reference deposits with ``zeta(theta) = zeta_0 * cos^2(pi/2 * (theta /
theta_c)^2) * cos(theta)^p`` (:mod:`dm2.reference.model`); ``p = 0`` is the model's own curve,
flat near normal impact. A cell whose curve falls off sooner (a powder and substrate whose
efficiency drops almost linearly with the spray angle) builds less on every slope than that
reference: its walls, edges and flanks read as underbuild on a part with no defect. Within one
layer that shortfall cannot be told apart from a process change (a feed step, an efficiency
drift) on parts without a large flat interior, so it is fitted here, offline, from a build the
user knows to be fault-free, once per cell and powder, like the uncertainty model
(:mod:`dm2.defects.uncertainty_fit`).

The fit is Gauss-Newton on the whole pipeline: the recording is replayed at the current
exponent ``p`` and at ``p + PROBE_STEP``; the change of every observed vertex's signed
deviation between the two is its sensitivity ``s``, and the step is the least-squares
``-sum(d * s) / sum(s * s)`` over the vertices observed in both replays, inside the planned
outline, with ``|d| <= OUTLIER_MM``. It repeats until the step is below ``TOLERANCE`` (at most
``MAX_ITERATIONS`` steps) and ends with a replay at the fitted value, whose residual is
reported. The exponent stays in ``EXPONENT_RANGE``: a step held at a bound ends the fit there,
said so (``at_bound``); a cell whose curve is flatter than the model's reads 0. A recording
whose part has no slopes (``sum(s * s)`` below ``MIN_SENSITIVITY_MM2`` per vertex) does not
constrain the curve and is refused.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from dm2.core.config import MAX_EFFICIENCY_COS_EXPONENT, MonitorConfig, ProcessConfig
from dm2.defects.classify import CLASS_NAMES

PROBE_STEP = 1.0  # exponent step of the sensitivity replay
TOLERANCE = 0.05  # a step this small ends the fit
MAX_ITERATIONS = 4
OUTLIER_MM = 3.0  # deviations beyond this are not curve error (and not used)
MIN_SENSITIVITY_MM2 = 1e-4  # mean s^2 [mm^2] per vertex below which the curve is not seen
EXPONENT_RANGE = (0.0, MAX_EFFICIENCY_COS_EXPONENT)  # the config's bounds
PAIR_MM = 0.01  # a vertex of one replay and the other's nearest within this are the same
_UNOBSERVED = CLASS_NAMES.index("unobserved")


class CurveNotObservable(ValueError):
    """The recording's part has no surface whose deposit depends on the curve."""


@dataclass
class CurveFit:
    """Outcome of :func:`fit_efficiency_exponent`.

    Attributes
    ----------
    exponent : float, the fitted ``efficiency_cos_exponent``
    start : float, the exponent the fit started from (the recording's configured one)
    iterations : list of dict, per Gauss-Newton step: ``exponent``, ``step`` (as taken, within
        the bounds), ``unbounded_step``, ``residual_rms_mm`` (at the step's start), ``vertices``
    residual_rms_mm : float [mm], RMS deviation of the usable vertices (observed, inside the
        planned outline, within ``OUTLIER_MM``) at ``exponent``
    start_rms_mm : float [mm], the same at ``start``
    at_bound : bool, the last step was held at a bound of :data:`EXPONENT_RANGE` (at 0: the
        cell's curve is no steeper than the model's; the model's own curve is the closest)
    tracks_at_start, tracks_at_fit : int, defect tracks the monitor raised on the recording
        at ``start`` and at ``exponent`` (a fault-free build: both ideally 0)
    """

    exponent: float
    start: float
    iterations: list[dict] = field(default_factory=list)
    residual_rms_mm: float = float("nan")
    start_rms_mm: float = float("nan")
    tracks_at_start: int = 0
    tracks_at_fit: int = 0
    at_bound: bool = False


@dataclass
class _Replay:
    deviations: dict  # layer -> (vertices_O (n, 3), signed deviation (n,), usable (n,) bool)
    tracks: int


def _replay(run_pipeline: Callable[[ProcessConfig], tuple], process: ProcessConfig,
            exponent: float) -> _Replay:
    proc = process.model_copy(update={"efficiency_cos_exponent": float(exponent)})
    results, tracks = run_pipeline(proc)
    deviations = {}
    for r in results:
        dev = r.deviation
        d = np.asarray(dev.signed_distance_mm, dtype=np.float64)
        usable = (dev.class_code != _UNOBSERVED) & np.isfinite(d) & (np.abs(d) <= OUTLIER_MM)
        if dev.outside_mm is not None:
            usable &= np.asarray(dev.outside_mm) <= 0.0
        deviations[r.layer] = (np.asarray(dev.vertices_O), d, usable)
    return _Replay(deviations, len(tracks))


def _paired(a: _Replay, b: _Replay):
    """Deviations of the vertices usable in both replays, layer by layer. The fused surface
    does not depend on the reference, but the meshing of a layer may run at another moment
    of the replay and move a vertex by float rounding: vertices are paired with the other
    replay's nearest within ``PAIR_MM``."""
    from scipy.spatial import cKDTree

    d_a, d_b = [], []
    for layer, (v_a, da, ua) in a.deviations.items():
        if layer not in b.deviations or not len(v_a):
            continue
        v_b, db, ub = b.deviations[layer]
        if not len(v_b):
            continue
        dist, j = cKDTree(v_b).query(v_a)
        both = ua & ub[j] & (dist <= PAIR_MM)
        d_a.append(da[both])
        d_b.append(db[j[both]])
    if not d_a:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(d_a), np.concatenate(d_b)


def _rms(d: np.ndarray) -> float:
    return float(np.sqrt(np.mean(d * d))) if d.size else float("nan")


def _replay_rms(replay: _Replay) -> float:
    """RMS deviation over one replay's usable vertices (what start and fit are compared by)."""
    d = [dev[usable] for _, dev, usable in replay.deviations.values()]
    return _rms(np.concatenate(d)) if d else float("nan")


def fit_efficiency_exponent(run_pipeline: Callable[[ProcessConfig], tuple],
                            process: ProcessConfig,
                            progress: Callable[[str], None] | None = None) -> CurveFit:
    """Fit ``efficiency_cos_exponent`` so that a fault-free build's deviations vanish in the
    least-squares sense (see the module docstring).

    Parameters
    ----------
    run_pipeline : ``f(process) -> (results, tracks)``: the recording replayed through a fresh
        pipeline with that process configuration; its analysed
        :class:`~dm2.defects.layer_analysis.LayerResult` list and its tracks
    process : the recording's process configuration (the fit starts at its exponent)
    progress : called with a line after each replay

    Raises
    ------
    CurveNotObservable : the part's deposit does not depend on the curve
    """
    lo, hi = EXPONENT_RANGE
    start = float(process.efficiency_cos_exponent)
    p = start
    here = _replay(run_pipeline, process, p)
    fit = CurveFit(exponent=p, start=start, tracks_at_start=here.tracks,
                   start_rms_mm=_replay_rms(here))
    for _ in range(MAX_ITERATIONS):
        h = PROBE_STEP if p + PROBE_STEP <= hi else -PROBE_STEP
        probe = _replay(run_pipeline, process, p + h)
        d0, d1 = _paired(here, probe)
        s = (d1 - d0) / h
        if not d0.size or float(np.mean(s * s)) < MIN_SENSITIVITY_MM2:
            raise CurveNotObservable(
                f"the recording's part shows no deposit that depends on the spray angle "
                f"({d0.size} usable vertices, mean sensitivity "
                f"{float(np.mean(s * s)) if s.size else 0.0:.2e} mm^2 per unit exponent): "
                "record a part with walls or slopes")
        step = -float(np.dot(d0, s) / np.dot(s, s))
        new = float(np.clip(p + step, lo, hi))
        fit.at_bound = new != p + step
        fit.iterations.append({"exponent": p, "step": new - p, "unbounded_step": step,
                               "residual_rms_mm": _rms(d0), "vertices": int(d0.size)})
        if progress is not None:
            progress(f"exponent {p:.3f}: residual RMS {_rms(d0):.4f} mm over {d0.size} "
                     f"vertices, step {new - p:+.3f}"
                     + (f" (the bound; unbounded {step:+.3f})" if fit.at_bound else ""))
        if new == p:  # held at a bound: nothing to replay
            break
        p = new
        here = _replay(run_pipeline, process, p)
        if abs(fit.iterations[-1]["step"]) < TOLERANCE:
            break
    fit.exponent, fit.residual_rms_mm, fit.tracks_at_fit = p, _replay_rms(here), here.tracks
    return fit


def recording_pipeline(messages: Callable[[], Iterable], calibration, monitor_cfg: MonitorConfig,
                       plate_size_mm, toolpath=None) -> Callable[[ProcessConfig], tuple]:
    """``run_pipeline`` for :func:`fit_efficiency_exponent`: each call replays
    ``messages()`` (a fresh iterator of the recording) through a new
    :class:`~dm2.pipeline.pipeline.Pipeline` behind the input gates."""
    from dm2.fusion.gates import InputGates
    from dm2.pipeline.pipeline import Pipeline

    def run(process: ProcessConfig):
        pipeline = Pipeline(calibration, monitor_cfg, process, plate_size_mm=plate_size_mm,
                            toolpath=toolpath, gates=InputGates(monitor_cfg.gates))
        results = pipeline.run(messages())
        return results, pipeline.tracks

    return run
