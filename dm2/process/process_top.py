"""Where the process fit (:mod:`dm2.process.process_fit`) reads the part: the top's vertices,
the plateau where the deposition scale shows, the places where the plume width does not move
the reference, and the plume width that the first layer's edges show."""

from __future__ import annotations

import numpy as np

from dm2.defects.classify import DEFECT_CLASSES, UNOBSERVED
from dm2.process.calibration_top import weighted_median

TOP_NZ = 0.95  # |n_z| of a vertex counted as the part's top
MIN_TOP_VERTICES = 50  # fewer top vertices: no estimate this layer
MIN_HEIGHT_MM = 0.2  # reference thinner than this on the top: no estimate
PLATEAU_SLOPE = 0.1  # reference slope [mm/mm] of the plateau the scale is measured on
PLATEAU_FRACTION = 0.7  # of the top's 95th-percentile reference height
PLUME_MIN_SENSITIVITY_MM = 0.05  # vertices whose height barely depends on the plume width
PLUME_DOUBT = 0.15  # a finding read on a plume-shaped top states what a plume this far off moves


def plume_factor(result, scale: float, bound: float) -> float:
    """The plume width against nominal that the first layer's edges show.

    A plume a fraction ``r`` wider moves the reference by ``r * P`` with ``P = sigma^2
    laplacian(h)`` (ReferenceMap.plume_sensitivity_at): the least-squares ``r`` of
    ``measured - scale * seen = scale * r * P`` over the observed, defect-free vertices within
    two plume widths of the outline where ``|P|`` matters (:func:`edge_samples`), one pass
    trimmed at 3 MAD."""
    samples = edge_samples(result)
    if samples is None:
        return 1.0
    seen, z, P, w = samples
    r = trimmed_lstsq((scale * P)[:, None], z - scale * seen, w)[0]
    return float(np.clip(1.0 + r, 1.0 - bound, 1.0 + bound))


def joint_plume_factor(result, bound: float) -> float:
    """The plume width against nominal that the first layer's edges show, fitted together
    with the scale: the least-squares ``(a, b)`` of ``measured = a * seen + b * P`` over the
    same vertices as :func:`plume_factor` (trimmed the same way), the plume ``1 + b / a``.
    For a top with no place to read the scale apart from the plume width."""
    samples = edge_samples(result)
    if samples is None:
        return 1.0
    seen, z, P, w = samples
    a, b = trimmed_lstsq(np.column_stack([seen, P]), z, w)
    if not a > 0:
        return 1.0
    return float(np.clip(1.0 + b / a, 1.0 - bound, 1.0 + bound))


def edge_samples(result) -> tuple[np.ndarray, ...] | None:
    """``(seen, measured, P, weight)`` at the layer's observed, defect-free, fresh vertices
    within two plume widths of the outline where ``|P| >= PLUME_MIN_SENSITIVITY_MM``: the
    reference as seen and the measured height [mm], ``P = sigma^2 laplacian(h)`` [mm] and the
    vertex area; None without a plume width or with fewer than ``MIN_TOP_VERTICES``."""
    ref = getattr(result, "reference", None)
    dev = result.deviation
    if ref is None or not ref.plume_sigma_mm > 0:
        return None
    ok = (dev.class_code != UNOBSERVED) & ~np.isin(dev.class_code, DEFECT_CLASSES)
    ok &= not_stale(dev)
    if dev.outside_mm is not None:
        ok &= dev.outside_mm <= 2.0 * ref.plume_sigma_mm
    P = ref.plume_sensitivity_at(dev.foot_O[:, :2])
    ok &= np.abs(P) >= PLUME_MIN_SENSITIVITY_MM
    if ok.sum() < MIN_TOP_VERTICES:
        return None
    seen = dev.foot_O[ok, 2]
    if getattr(dev, "unseen_mm", None) is not None:
        seen = seen - dev.unseen_mm[ok]
    area = getattr(dev, "vertex_area_mm2", None)
    w = np.ones(seen.size) if area is None else np.asarray(area)[ok]
    return seen, dev.vertices_O[ok, 2], P[ok], w


def trimmed_lstsq(X: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least squares of ``X (n, k) c = y``, then once more without the residuals
    beyond 3 MAD when ``MIN_TOP_VERTICES`` remain."""
    def solve(m):
        sw = np.sqrt(w[m])
        return np.linalg.lstsq(X[m] * sw[:, None], y[m] * sw, rcond=None)[0]

    every = np.ones(y.size, bool)
    c = solve(every)
    res = y - X @ c
    mad = float(np.median(np.abs(res - np.median(res)))) * 1.4826
    keep = np.abs(res) <= 3.0 * max(mad, 1e-6)
    return solve(keep) if keep.sum() >= MIN_TOP_VERTICES else c


def on_plateau(reference, foot_O, top) -> np.ndarray:
    """Vertices whose reference is on the part's plateau: slope at most ``PLATEAU_SLOPE`` and
    at least ``PLATEAU_FRACTION`` of the top's 95th-percentile height. The edges' ramps are
    left out: there the plume width decides the height (a plume a few per cent wider than
    modelled lowers them), not the deposition scale."""
    if reference is None or not np.any(top):
        return np.ones(top.shape, bool)
    h = foot_O[:, 2]
    slope = np.linalg.norm(reference.gradient_at(foot_O[:, :2]), axis=-1)
    return (slope <= PLATEAU_SLOPE) & (h >= PLATEAU_FRACTION * np.percentile(h[top], 95))


def plume_insensitive(reference, xy_O: np.ndarray, enough: int) -> np.ndarray | None:
    """The calibration's scale is read where the plume width does not matter: the mask of the
    points ``xy_O (n, 2)`` [mm] where ``reference`` (a ReferenceMap) moves less than
    ``PLUME_MIN_SENSITIVITY_MM`` with its plume width (its ``sigma^2 laplacian``,
    :meth:`ReferenceMap.plume_sensitivity_at`), or None when fewer than ``enough`` are, or
    without a reference whose plume width is known.

    A narrow part's plateau is not flat at the plume's scale: on a 7 mm wide ring its
    ``sigma^2 laplacian`` is -0.17 mm at the median, so a plume 15 % wider than modelled lowers
    it by 0.03 mm, 3 % of a first layer, and a scale read there comes out that much low. The
    plume width is then fitted at that scale on the edges, where it does matter
    (:func:`plume_factor`). A part with no such top (a bracket's thin walls) keeps the
    whole plateau."""
    if reference is None or not reference.plume_sigma_mm > 0 or not len(xy_O):
        return None
    flat = np.abs(reference.plume_sensitivity_at(xy_O)) < PLUME_MIN_SENSITIVITY_MM
    return flat if flat.sum() >= enough else None


def top_heights(seen_ref: np.ndarray, z: np.ndarray, area: np.ndarray) -> tuple[float, float]:
    """``(reference, measured)`` top heights [mm]: the reference's area-weighted median, and
    the measured top as the reference's plus the median difference (a flat top's
    marching-cubes vertices crowd at the voxel-centre levels, so their own median sticks to a
    voxel plane, 0.1 mm low on a thin first layer)."""
    ref = weighted_median(seen_ref, area)
    return ref, ref + weighted_median(z - seen_ref, area)


def normals_z(dev) -> np.ndarray:
    """|n_z| (n,) of the layer mesh's vertex normals."""
    from dm2.defects.classify import curvature_and_areas

    if dev.normals_O is not None:
        return np.abs(dev.normals_O[:, 2])
    if dev.n_vertices == 0:
        return np.zeros(0)
    _, _, normals = curvature_and_areas(dev.vertices_O, dev.faces, return_normals=True,
                                        smooth_iterations=0)
    return np.abs(normals[:, 2])


def not_stale(dev) -> np.ndarray | bool:
    """The vertices that are a surface the profilers saw: a stale top (dm2.defects.stale) is
    an old one, not the process's."""
    stale = getattr(dev, "stale_mm", None)
    return True if stale is None else np.asarray(stale) == 0.0


def plume_share(reference, xy_O: np.ndarray, area: np.ndarray, top_mm: float) -> float | None:
    """How much of the top's height moves per relative change of the plume width: the
    area-weighted median ``|sigma^2 laplacian|`` of ``reference`` (a ReferenceMap) at the top's
    points ``xy_O (n, 2)`` [mm] over the top's height ``top_mm``; None without a plume width.

    On a top with no place where the plume width does not matter (:func:`plume_insensitive`:
    a thin wall, a 10 mm bar) the deposition scale is read where a plume wider than the model's
    lowers the top as a lower efficiency would: a plume a fraction ``r`` off moves the scale read
    there by about ``r`` times this share. The process finding says so (PLUME_DOUBT)."""
    if reference is None or not reference.plume_sigma_mm > 0 or not top_mm > 0 or not len(xy_O):
        return None
    p = np.abs(reference.plume_sensitivity_at(xy_O))
    return float(weighted_median(p, np.asarray(area, np.float64)) / top_mm)


def plume_lift(reference, xy_O: np.ndarray, area: np.ndarray, top_mm: float) -> float:
    """How a plume wider than the model's moves the top: the area-weighted median ``sigma^2
    laplacian`` of ``reference`` at the top's points ``xy_O (n, 2)`` [mm] over the top's height
    ``top_mm``, signed (negative on a ridge, which a wider plume lowers); 0 without a plume
    width."""
    if reference is None or not reference.plume_sigma_mm > 0 or not top_mm > 0 or not len(xy_O):
        return 0.0
    p = reference.plume_sensitivity_at(xy_O)
    return float(weighted_median(p, np.asarray(area, np.float64)) / top_mm)


def joint_scale_plume(result, est: float, lift: float, scale_bound: float,
                      plume_bound: float) -> tuple[float, float]:
    """``(scale, plume)`` of the calibration layer, ``est`` the scale read on its top as if the
    plume were the model's.

    On a top with a place where the plume width does not matter (``lift`` 0) ``est`` is the
    scale, and the plume is fitted on the edges at it (:func:`plume_factor`). On a top the
    plume shapes, the plume is fitted together with a scale on the edges
    (:func:`joint_plume_factor`), and a plume a factor ``p`` wide moves the top by ``(p - 1) *
    lift`` of its height (:func:`plume_lift`): the scale is ``est / (1 + (p - 1) * lift)``."""
    if lift == 0.0:
        scale = float(np.clip(est, 1.0 - scale_bound, 1.0 + scale_bound))
        return scale, plume_factor(result, scale, plume_bound)
    plume = joint_plume_factor(result, plume_bound)
    return scale_under_plume(est, plume, lift, scale_bound), plume


def scale_under_plume(est: float, plume: float, lift: float, bound: float) -> float:
    """The scale ``est`` read on a top as if the plume were the model's, for a plume ``plume``
    times as wide that moves the top by ``(plume - 1) * lift`` of its height, within ``1 +-
    bound``."""
    return float(np.clip(est / max(1.0 + (plume - 1.0) * lift, 0.5), 1.0 - bound, 1.0 + bound))
