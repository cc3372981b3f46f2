"""What the near-net reference deposited, brought to another plume width
(:meth:`dm2.reference.model.NearNetReference.set_plume_factor`, the process fit's plume
calibration).

A Gaussian footprint is a heat kernel: a plume ``factor`` times as wide deposits what the
narrower one did, blurred by ``sigma * sqrt(factor^2 - 1)``. A narrower plume is the first-order
step ``h + (factor - 1) sigma^2 laplacian(h)`` (kept non-negative). Either filter runs on the
box of the plate that holds deposit, widened by its reach: the heights are the same as when the
whole plate is filtered, in a fraction of the time for a small part on a large plate.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter, laplace

GAUSSIAN_TRUNCATE = 4.0  # the widening blurs out to 4 sigmas (scipy's default)


def rescale_plume(heights_mm: np.ndarray, cell_mm: float, sigma_mm: float,
                  factor: float) -> None:
    """Bring ``heights_mm`` (ny, nx) [mm], deposited with a plume of ``sigma_mm``, to the plume
    ``factor`` times as wide, in place."""
    if factor > 1.0:
        blur_px = sigma_mm * np.sqrt(factor * factor - 1.0) / cell_mm
        box = deposit_box(heights_mm, int(GAUSSIAN_TRUNCATE * blur_px + 0.5) + 1)
        if box is not None:
            heights_mm[box] = gaussian_filter(heights_mm[box], blur_px, mode="nearest",
                                              truncate=GAUSSIAN_TRUNCATE)
    elif factor < 1.0:
        box = deposit_box(heights_mm, 2)
        if box is not None:
            h = heights_mm[box]
            lap = laplace(h, mode="nearest") / (cell_mm * cell_mm)
            heights_mm[box] = np.maximum(h + (factor - 1.0) * sigma_mm ** 2 * lap, 0.0)


def deposit_box(heights_mm: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """The grid's rows and columns holding deposit, widened by ``margin`` cells (clipped to the
    plate), or None before any deposit. A filter whose support is at most ``margin - 1`` cells
    gives the same heights on this box as on the whole plate (everything outside it is 0 before
    and after)."""
    rows = np.flatnonzero(heights_mm.any(axis=1))
    if not len(rows):
        return None
    cols = np.flatnonzero(heights_mm[rows[0]:rows[-1] + 1].any(axis=0))
    ny, nx = heights_mm.shape
    return (slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, ny)),
            slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, nx)))
