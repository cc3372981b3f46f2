"""Injected process faults (scenario ``[[faults]]``) and calibration perturbation.

Each fault acts inside a window: ``layers = [first, last]`` (inclusive) and/or
``time_s = [start, end]`` (process seconds); with both, the window is their intersection; with
neither, the whole build. Progress ``u`` through a window runs 0 -> 1 over the time window, or
per layer as ``(layer - first + 0.5) / (last - first + 1)`` for a layer window.

========================  =====================================================================
kind                      effect
========================  =====================================================================
``feed_step``             feed x ``factor`` from the window start on (the window end is ignored)
``feed_drift``            feed ramps linearly 1 -> ``factor`` across the window, then holds
``feed_drop``             feed x ``factor`` inside the window only
``clog``                  feed dips 1 -> ``factor`` -> 1 as ``1 - (1 - factor) sin(pi u)``
``efficiency_drift``      deposition efficiency x ``(1 + per_layer * n)``, n = layers since the
                          window start (inclusive), held after the window (layer windows only;
                          or a constant ``factor`` inside the window)
``standoff_change``       standoff + ``delta_mm`` inside the window (wider, flatter plume)
``bump`` / ``dent``       a Gaussian blob of peak ``height_mm`` and full width at half maximum
                          ``width_mm`` at ``center_O_mm`` is added / removed at the end of every
                          layer of the window
``corner_dwell``          ``extra_dwell_s`` stop at every spraying toolpath corner whose interior
                          angle is within ``CORNER_TOL_DEG`` of ``corner_angle_deg`` (layer window)
========================  =====================================================================

Several feed faults multiply, efficiency faults multiply, standoff changes add.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from dm2.core.frames import make_T
from dm2.core.messages import Calibration, Toolpath
from dm2.core.tolerances import DIVISOR_FLOOR, SAME_POINT_MM
from twin.schema import CalibrationPerturbation, FaultConfig

log = logging.getLogger(__name__)

CORNER_TOL_DEG = 5.0
FEED_KINDS = ("feed_step", "feed_drift", "feed_drop", "clog")
BLOB_KINDS = ("bump", "dent")
_REQUIRED = {
    "feed_step": ("factor",), "feed_drift": ("factor",), "feed_drop": ("factor",),
    "clog": ("factor",), "efficiency_drift": (), "standoff_change": ("delta_mm",),
    "bump": ("center_O_mm", "height_mm", "width_mm", "layers"),
    "dent": ("center_O_mm", "height_mm", "width_mm", "layers"),
    "corner_dwell": ("corner_angle_deg", "extra_dwell_s"),
}


def check_fault(f: FaultConfig, index: int = 0, n_layers: int | None = None) -> None:
    """Raise ``ValueError`` naming ``faults[index]`` if a field its kind needs is missing, or
    its layer window is negative or (with ``n_layers``, the part's layer count) starts beyond
    the part's last layer, where the fault would never act."""
    missing = [k for k in _REQUIRED[f.kind] if getattr(f, k) is None]
    if f.kind == "efficiency_drift":
        if f.per_layer is None and f.factor is None:
            missing.append("per_layer (or factor)")
        if f.per_layer is not None and f.layers is None:
            missing.append("layers")
    if missing:
        raise ValueError(f"faults[{index}] (kind '{f.kind}'): missing {', '.join(missing)}")
    if f.factor is not None and f.factor < 0:
        raise ValueError(f"faults[{index}] (kind '{f.kind}'): factor must be >= 0 "
                         f"(got {f.factor})")
    if f.layers is not None:
        if f.layers[0] < 0:
            raise ValueError(f"faults[{index}].layers: {list(f.layers)} starts below layer 0")
        if n_layers is not None and f.layers[0] > n_layers - 1:
            raise ValueError(f"faults[{index}].layers: {list(f.layers)} starts beyond the "
                             f"part's last layer {n_layers - 1} (layers 0..{n_layers - 1}); "
                             "the fault would never act")
    if f.time_s is not None and f.time_s[0] < 0:
        raise ValueError(f"faults[{index}].time_s: {list(f.time_s)} starts before 0 s")


def _in_window(f: FaultConfig, t, layer, open_end: bool = False):
    t = np.asarray(t, dtype=np.float64)
    layer = np.asarray(layer)
    ok = np.ones(np.broadcast(t, layer).shape, dtype=bool)
    if f.time_s is not None:
        ok &= t >= f.time_s[0]
        if not open_end:
            ok &= t <= f.time_s[1]
    if f.layers is not None:
        ok &= layer >= f.layers[0]
        if not open_end:
            ok &= layer <= f.layers[1]
    return ok


def _progress(f: FaultConfig, t, layer):
    t = np.asarray(t, dtype=np.float64)
    layer = np.asarray(layer, dtype=np.float64)
    if f.time_s is not None:
        span = max(f.time_s[1] - f.time_s[0], DIVISOR_FLOOR)
        return np.clip((t - f.time_s[0]) / span, 0.0, 1.0) + 0.0 * layer
    if f.layers is not None:
        n = f.layers[1] - f.layers[0] + 1
        return np.clip((layer - f.layers[0] + 0.5) / n, 0.0, 1.0) + 0.0 * t
    return np.ones(np.broadcast(t, layer).shape)


def _out(x, scalar: bool):
    return float(x) if scalar else np.asarray(x, dtype=np.float64)


class FaultSchedule:
    """The scenario's faults as functions of process time and layer.

    Parameters
    ----------
    faults : sequence of FaultConfig
    toolpath : Toolpath, optional; needed for :meth:`corner_dwell_s` defaults
    cell : optional cell model (unused by the fault models; accepted for a uniform call)
    """

    def __init__(self, faults: Sequence[FaultConfig] = (), toolpath: Toolpath | None = None,
                 cell=None):
        self.faults = tuple(faults)
        n_layers = int(toolpath.layer.max()) + 1 if toolpath is not None and \
            len(toolpath.layer) else None
        for i, f in enumerate(self.faults):
            check_fault(f, i, n_layers)
        self.toolpath = toolpath
        self.cell = cell

    def feed_factor(self, t_s, layer):
        """Powder feed multiplier at ``t_s`` [s] in ``layer`` (scalars or broadcastable arrays)."""
        scalar = np.ndim(t_s) == 0 and np.ndim(layer) == 0
        out = np.ones(np.broadcast(np.asarray(t_s), np.asarray(layer)).shape)
        for f in self.faults:
            if f.kind not in FEED_KINDS:
                continue
            if f.kind == "feed_step":
                out = out * np.where(_in_window(f, t_s, layer, open_end=True), f.factor, 1.0)
            elif f.kind == "feed_drop":
                out = out * np.where(_in_window(f, t_s, layer), f.factor, 1.0)
            elif f.kind == "feed_drift":
                started = _in_window(f, t_s, layer, open_end=True)
                u = np.where(_in_window(f, t_s, layer), _progress(f, t_s, layer), 1.0)
                out = out * np.where(started, 1.0 + (f.factor - 1.0) * u, 1.0)
            else:  # clog
                u = _progress(f, t_s, layer)
                dip = 1.0 - (1.0 - f.factor) * np.sin(np.pi * u)
                out = out * np.where(_in_window(f, t_s, layer), dip, 1.0)
        return _out(out, scalar)

    def efficiency_factor(self, layer):
        """Deposition-efficiency multiplier for ``layer`` (scalar or array)."""
        scalar = np.ndim(layer) == 0
        layer = np.asarray(layer)
        out = np.ones(layer.shape)
        for f in self.faults:
            if f.kind != "efficiency_drift":
                continue
            if f.per_layer is not None:
                first, last = f.layers
                n = np.clip(layer, None, last) - first + 1
                out = out * np.where(layer >= first, np.maximum(1.0 + f.per_layer * n, 0.0), 1.0)
            else:
                inside = np.ones(layer.shape, bool) if f.layers is None else \
                    (layer >= f.layers[0]) & (layer <= f.layers[1])
                out = out * np.where(inside, f.factor, 1.0)
        return _out(out, scalar)

    def standoff_delta_mm(self, t_s, layer):
        """Change of the spray standoff [mm] at ``t_s`` in ``layer``."""
        scalar = np.ndim(t_s) == 0 and np.ndim(layer) == 0
        out = np.zeros(np.broadcast(np.asarray(t_s), np.asarray(layer)).shape)
        for f in self.faults:
            if f.kind == "standoff_change":
                out = out + np.where(_in_window(f, t_s, layer), f.delta_mm, 0.0)
        return _out(out, scalar)

    def corner_dwell_s(self, toolpath: Toolpath | None = None) -> np.ndarray:
        """Extra stop [s] at each toolpath vertex, (n,) (zeros without corner faults)."""
        tp = self.toolpath if toolpath is None else toolpath
        if tp is None:
            raise ValueError("FaultSchedule.corner_dwell_s: no toolpath given")
        dwell = np.zeros(len(tp))
        for f in self.faults:
            if f.kind != "corner_dwell":
                continue
            idx = find_corners(tp, f.corner_angle_deg)
            if f.layers is not None:
                lay = tp.layer[idx]
                idx = idx[(lay >= f.layers[0]) & (lay <= f.layers[1])]
            dwell[idx] += f.extra_dwell_s
            log.info("corner_dwell: %d corners of %.0f deg get %.2f s", len(idx),
                     f.corner_angle_deg, f.extra_dwell_s)
        return dwell

    def apply_blobs(self, hf, layer: int) -> int:
        """Add bumps / cut dents whose window holds ``layer`` (called as that layer starts, so
        the layer's own scans see the blob); returns how many."""
        count = 0
        for f in self.faults:
            if f.kind not in BLOB_KINDS or not f.layers[0] <= layer <= f.layers[1]:
                continue
            blob = blob_heights(hf, f.center_O_mm, f.height_mm, f.width_mm)
            hf.add_heights(blob if f.kind == "bump" else -blob)
            count += 1
            log.info("%s of %.2f mm at %s as layer %d starts", f.kind, f.height_mm, f.center_O_mm,
                     layer)
        return count


def blob_heights(hf, center_O_mm, height_mm: float, width_mm: float) -> np.ndarray:
    """(ny, nx) Gaussian blob [mm]: peak ``height_mm``, FWHM ``width_mm`` at ``center_O_mm``."""
    x, y = hf.centres_mm()
    s = width_mm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    gx = np.exp(-((x - center_O_mm[0]) ** 2) / (2 * s * s))
    gy = np.exp(-((y - center_O_mm[1]) ** 2) / (2 * s * s))
    return height_mm * np.outer(gy, gx)


def interior_angles_deg(position_O: np.ndarray, chord_mm: float) -> np.ndarray:
    """Interior angle [deg] of the path at each vertex: 180 minus the turn between the path's
    direction ``chord_mm .. 2 chord_mm`` of arc length before the vertex and the direction the
    same distance after it, so a rounded (blended) corner reads as its sharp angle when
    ``chord_mm`` exceeds the blend. 180 on straight runs and at the path ends."""
    p = np.asarray(position_O, dtype=np.float64)
    n = len(p)
    if n < 3:
        return np.full(n, 180.0)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])

    def at(q):
        return np.column_stack([np.interp(q, s, p[:, k]) for k in range(3)])

    back = at(s - chord_mm) - at(s - 2 * chord_mm)
    fwd = at(s + 2 * chord_mm) - at(s + chord_mm)
    nb = np.linalg.norm(back, axis=1)
    nf = np.linalg.norm(fwd, axis=1)
    ok = (nb > SAME_POINT_MM) & (nf > SAME_POINT_MM)
    cos = np.ones(n)
    cos[ok] = np.einsum("ij,ij->i", back[ok], fwd[ok]) / (nb[ok] * nf[ok])
    return 180.0 - np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def find_corners(tp: Toolpath, corner_angle_deg: float, tol_deg: float = CORNER_TOL_DEG,
                 chord_mm: float | None = None) -> np.ndarray:
    """Indices of spraying toolpath vertices at corners of interior angle ``corner_angle_deg``.

    One index per corner: where rounding spread a corner over several vertices, the vertex of
    sharpest turn is kept.
    """
    if len(tp) < 3:
        return np.zeros(0, dtype=np.int64)
    if chord_mm is None:
        chord_mm = max(2.0 * float(np.max(tp.zone_mm)), 1.0)
    ang = np.full(len(tp), 180.0)
    for lay in np.unique(tp.layer):  # measured within each layer: layer changes are no corners
        sel = np.flatnonzero(tp.layer == lay)
        ang[sel] = interior_angles_deg(tp.position_O[sel], chord_mm)
    match = (np.abs(ang - corner_angle_deg) <= tol_deg) & tp.spray_on
    sharp = ang < 179.0
    out = []
    k = 0
    n = len(tp)
    while k < n:
        if not sharp[k]:
            k += 1
            continue
        j = k
        while j + 1 < n and sharp[j + 1] and tp.layer[j + 1] == tp.layer[k]:
            j += 1
        run = np.arange(k, j + 1)
        sharpest = run[ang[run] <= ang[run].min() + 0.5]
        best = sharpest[len(sharpest) // 2]
        if match[best]:
            out.append(best)
        k = j + 1
    return np.asarray(out, dtype=np.int64)


def perturbed_calibration(true_cal: Calibration, pert: CalibrationPerturbation | None
                          ) -> Calibration:
    """The calibration handed to the pipeline: each listed sensor's pose is moved by
    ``translation_mm`` and rotated by ``rotation_deg`` (x-y-z angles), both in that sensor's own
    frame: ``T_B_S' = T_B_S @ T_err``. ``None`` returns the true calibration."""
    if pert is None:
        return true_cal
    unknown = [s for s in pert.sensors if s not in true_cal.T_B_S]
    if unknown:
        raise ValueError(f"calibration_error.sensors: {unknown} not in the calibration "
                         f"({sorted(true_cal.T_B_S)})")
    T_err = make_T(Rotation.from_euler("xyz", pert.rotation_deg, degrees=True),
                   np.asarray(pert.translation_mm, dtype=np.float64))
    poses = {sid: (T @ T_err if sid in pert.sensors else T.copy())
             for sid, T in true_cal.T_B_S.items()}
    return Calibration(T_B_S=poses, T_F_O=true_cal.T_F_O.copy(), T_B_N=true_cal.T_B_N.copy())
