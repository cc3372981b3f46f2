"""Ground truth the twin writes beside a run: true surfaces per layer and what each fault did.

* :func:`write_layer_surface`: the true top surface at the end of a layer as a PLY mesh in O
  [mm] (cropped to the built region plus a margin unless ``full=True``).
* :func:`write_deviation_maps`: per layer the true deviation the faults caused (faulty minus
  fault-free surface) as a height-field map in O, ``deviation_LLL.npz`` (the format of
  ``dm2.bench.truth_maps``, which the bench scores against).
* :func:`fault_truth` / :func:`write_fault_truth`: for every injected fault its region in O,
  sign (+1 overbuild, -1 underbuild), the layers it visibly affects and the deviation it causes,
  measured against a fault-free run with the same seed (the difference of two height fields).

Fault-truth JSON::

    {"schema": 1, "threshold_mm": 0.05,
     "faults": [{"id": 0, "kind": "feed_drop", "sign": -1, "layers": [3, 4, ...],
                 "region_O": {"bbox": [xmin, ymin, xmax, ymax], "centers": [[x, y], ...]},
                 "expected_deviation_mm": -0.61,
                 "deviation_by_layer_mm": {"0": 0.0, ...}}, ...]}

Global faults (feed, efficiency, standoff) report the median height difference over the part's
footprint; local faults (bump, dent, corner dwell) the extreme difference in their region.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from dm2.core.messages import Toolpath
from dm2.core.tolerances import BUILT_HEIGHT_MM
from twin.schema import FaultConfig
from twin.world.faults import find_corners
from twin.world.heightfield import HeightField

log = logging.getLogger(__name__)

TRUTH_SCHEMA = 1
LOCAL_KINDS = ("bump", "dent", "corner_dwell")
CORNER_RADIUS_MM = 6.0  # region around a dwelled corner: about two plume sigmas
SURFACE_MARGIN_MM = 10.0


def write_layer_surface(hf: HeightField, path, full: bool = False,
                        margin_mm: float = SURFACE_MARGIN_MM) -> Path:
    """Write the true top surface as PLY (binary) in O [mm]; returns the path written.

    Without ``full`` the mesh covers the cells with material (height above 1 um) plus
    ``margin_mm`` of bare plate around them; a bare plate is written whole.
    """
    path = Path(path)
    window = None
    if not full:
        built = np.abs(hf.heights_mm) > BUILT_HEIGHT_MM
        if built.any():
            x, y = hf.centres_mm()
            cols = np.flatnonzero(built.any(axis=0))
            rows = np.flatnonzero(built.any(axis=1))
            window = (x[cols[0]] - margin_mm, y[rows[0]] - margin_mm,
                      x[cols[-1]] + margin_mm, y[rows[-1]] + margin_mm)
    mesh = hf.to_mesh(window_mm=window)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    tmp.write_bytes(mesh.export(file_type="ply"))
    tmp.replace(path)
    return path


def _as_layers(fields) -> dict[int, np.ndarray]:
    if isinstance(fields, Mapping):
        items = fields.items()
    else:
        items = enumerate(fields)
    return {int(k): np.asarray(v.heights_mm if isinstance(v, HeightField) else v,
                               dtype=np.float64) for k, v in items}


def _cell_of(fields) -> float | None:
    for v in (fields.values() if isinstance(fields, Mapping) else fields):
        if isinstance(v, HeightField):
            return v.cell_mm
    return None


def _default_sign(f: FaultConfig) -> int:
    if f.kind in ("bump", "corner_dwell"):
        return 1
    if f.kind == "dent":
        return -1
    if f.kind == "efficiency_drift":
        if f.per_layer is not None:
            return 1 if f.per_layer > 0 else -1
        return 1 if f.factor > 1 else -1
    if f.factor is not None:
        return 1 if f.factor > 1 else -1
    return -1  # a standoff change widens or narrows the plume; the centre loses either way


def fault_truth(faults: Sequence[FaultConfig], hf_faulty_by_layer, hf_nominal_by_layer,
                toolpath: Toolpath | None = None, cell_mm: float | None = None,
                threshold_mm: float = 0.05, footprint_fraction: float = 0.9,
                area_threshold_mm: float | None = None) -> dict:
    """What each fault did, from the faulty and fault-free height fields per layer.

    Parameters
    ----------
    faults : the scenario's FaultConfig list (ids are their indices)
    hf_faulty_by_layer, hf_nominal_by_layer : mapping layer -> HeightField (or (ny, nx) heights
        [mm], then ``cell_mm`` is required), or sequences indexed by layer; same seed
    toolpath : needed for ``corner_dwell`` regions
    threshold_mm : a layer counts as affected when the fault's deviation reaches this
    footprint_fraction : global faults are measured where the nominal final height exceeds
        this fraction of its 95th percentile (their region bbox is where it exceeds half)
    area_threshold_mm : when given (the monitor's global tolerance), each fault also reports
        per layer the projected area [mm^2] where its deviation, in its sign, exceeds this —
        the area a monitor with that tolerance should flag (``area_mm2_by_layer``)
    """
    faulty = _as_layers(hf_faulty_by_layer)
    nominal = _as_layers(hf_nominal_by_layer)
    layers = sorted(set(faulty) & set(nominal))
    if not layers:
        raise ValueError("fault_truth: the faulty and nominal runs share no layer")
    c = _cell_of(hf_nominal_by_layer) or cell_mm
    if c is None:
        raise ValueError("fault_truth: give cell_mm when passing bare height arrays")
    shape = nominal[layers[-1]].shape
    for k in layers:
        if faulty[k].shape != shape or nominal[k].shape != shape:
            raise ValueError(f"fault_truth: layer {k} height fields differ in shape")
    x = (np.arange(shape[1]) + 0.5) * c
    y = (np.arange(shape[0]) + 0.5) * c
    gx, gy = np.meshgrid(x, y)
    final = nominal[layers[-1]]
    built = final > BUILT_HEIGHT_MM
    top = np.percentile(final[built], 95) if np.any(built) else 0.0
    footprint = final > footprint_fraction * top if top > 0 else np.ones(shape, bool)
    outline = final > 0.5 * top if top > 0 else np.ones(shape, bool)  # region of global faults

    out = []
    for i, f in enumerate(faults):
        centers = []
        if f.kind in ("bump", "dent"):
            centers = [list(f.center_O_mm)]
            radius = f.width_mm
        elif f.kind == "corner_dwell":
            if toolpath is None:
                raise ValueError(f"fault_truth: faults[{i}] is corner_dwell; give the toolpath")
            idx = find_corners(toolpath, f.corner_angle_deg)
            if f.layers is not None:
                lay = toolpath.layer[idx]
                idx = idx[(lay >= f.layers[0]) & (lay <= f.layers[1])]
            pts = np.unique(np.round(toolpath.position_O[idx, :2], 1), axis=0)
            centers = pts.tolist()
            radius = CORNER_RADIUS_MM
        if f.kind in LOCAL_KINDS:
            mask = np.zeros(shape, bool)
            for cx, cy in centers:
                mask |= (gx - cx) ** 2 + (gy - cy) ** 2 <= radius**2
            region = mask
        else:
            mask, region = footprint, outline
        sign0 = _default_sign(f)
        by_layer, area_by_layer = {}, {}
        area_mask = mask if f.kind in LOCAL_KINDS else np.ones(shape, bool)
        for k in layers:
            if area_threshold_mm is not None:
                dev_k = sign0 * (faulty[k] - nominal[k])[area_mask]
                area_by_layer[str(k)] = float(np.count_nonzero(dev_k > area_threshold_mm)) * c * c
            d = (faulty[k] - nominal[k])[mask]
            if d.size == 0:
                by_layer[k] = 0.0
            elif f.kind in LOCAL_KINDS:
                by_layer[k] = float(np.max(d) if sign0 > 0 else np.min(d))
            else:
                by_layer[k] = float(np.median(d))
        dev = by_layer[layers[-1]]
        sign = int(np.sign(dev)) if abs(dev) >= threshold_mm else sign0
        if region.any():
            bbox = [float(gx[region].min()), float(gy[region].min()),
                    float(gx[region].max()), float(gy[region].max())]
        else:
            bbox = [0.0, 0.0, float(x[-1] + 0.5 * c), float(y[-1] + 0.5 * c)]
        entry = {
            "id": i, "kind": f.kind, "sign": sign,
            "layers": [k for k in layers if (sign0 * by_layer[k] if f.kind in LOCAL_KINDS
                                             else abs(by_layer[k])) >= threshold_mm],
            "region_O": {"bbox": bbox, **({"centers": centers} if centers else {})},
            "expected_deviation_mm": dev,
            "deviation_by_layer_mm": {str(k): v for k, v in by_layer.items()},
        }
        if area_threshold_mm is not None:
            entry["area_threshold_mm"] = float(area_threshold_mm)
            entry["area_mm2_by_layer"] = area_by_layer
        out.append(entry)
        log.info("fault %d (%s): sign %+d, %.3f mm at layer %d", i, f.kind, sign, dev,
                 layers[-1])
    return {"schema": TRUTH_SCHEMA, "threshold_mm": threshold_mm, "faults": out}


def write_deviation_maps(truth_dir, hf_faulty_by_layer, hf_nominal_by_layer, cell_mm: float,
                         margin_mm: float = SURFACE_MARGIN_MM) -> list[Path]:
    """Write ``deviation_LLL.npz`` per layer: ``deviation_mm`` (faulty minus fault-free heights
    [mm], float32), ``surface_mm`` (the faulty true heights [mm], float32), ``cell_mm``, ``x0_mm``
    / ``y0_mm`` (O coordinates of the first cell's centre) and ``layer``. Every layer's map
    covers the same window: the cells with material in either run's last layer plus
    ``margin_mm``. Returns the paths written."""
    faulty = _as_layers(hf_faulty_by_layer)
    nominal = _as_layers(hf_nominal_by_layer)
    layers = sorted(set(faulty) & set(nominal))
    if not layers:
        return []
    last = layers[-1]
    built = (np.abs(faulty[last]) > BUILT_HEIGHT_MM) | (np.abs(nominal[last]) > BUILT_HEIGHT_MM)
    ny, nx = built.shape
    pad = int(math.ceil(margin_mm / cell_mm))
    if built.any():
        rows, cols = np.flatnonzero(built.any(axis=1)), np.flatnonzero(built.any(axis=0))
        r0, r1 = max(rows[0] - pad, 0), min(rows[-1] + pad + 1, ny)
        c0, c1 = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, nx)
    else:
        r0, r1, c0, c1 = 0, ny, 0, nx
    out = []
    for k in layers:
        path = Path(truth_dir) / f"deviation_{k:03d}.npz"
        tmp = path.with_name(path.name + ".part.npz")
        np.savez_compressed(
            tmp, deviation_mm=(faulty[k] - nominal[k])[r0:r1, c0:c1].astype(np.float32),
            surface_mm=faulty[k][r0:r1, c0:c1].astype(np.float32), cell_mm=float(cell_mm),
            x0_mm=(c0 + 0.5) * cell_mm, y0_mm=(r0 + 0.5) * cell_mm, layer=int(k))
        tmp.replace(path)
        out.append(path)
    return out


def write_fault_truth(path, faults: Sequence[FaultConfig], hf_faulty_by_layer,
                      hf_nominal_by_layer, toolpath: Toolpath | None = None, **kwargs) -> dict:
    """Compute :func:`fault_truth` and write it as JSON to ``path``; returns the dict."""
    truth = fault_truth(faults, hf_faulty_by_layer, hf_nominal_by_layer, toolpath, **kwargs)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(truth, indent=2), encoding="utf-8")
    tmp.replace(path)
    return truth
