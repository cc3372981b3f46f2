"""Analytic occluders for the virtual profilers: solids that block rays but are never measured.

The deposit and the plate are ray-cast on the height field; occluders such as the nozzle body
are closed-form ray/solid intersections in the robot base B, vectorised over rays. Every
``hit_t`` returns the distance [mm] along unit directions to the first entry into the solid
(``np.inf`` where the ray misses it); a ray that starts inside a solid is blocked at ``t = 0``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2.config import CellConfig
from dm2.frames import invert

_EPS = 1e-12


@dataclass(frozen=True)
class CylinderOccluder:
    """A solid capped cylinder, posed in the robot base.

    Attributes
    ----------
    T_B_C : (4, 4) float64, cylinder frame in B; the axis is +z_C from ``z_C = 0`` to ``length_mm``
    radius_mm : float [mm]
    length_mm : float [mm]
    name : str, used in logs and drop counts
    """

    T_B_C: np.ndarray
    radius_mm: float
    length_mm: float
    name: str = "cylinder"

    def __post_init__(self):
        T = np.asarray(self.T_B_C, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"{self.name}: T_B_C must be a finite (4, 4) transform")
        if not (self.radius_mm > 0 and self.length_mm > 0):
            raise ValueError(f"{self.name}: radius_mm and length_mm must be positive")
        object.__setattr__(self, "T_B_C", T)
        object.__setattr__(self, "_T_C_B", invert(T))

    def hit_t(self, origins_B: np.ndarray, dirs_B: np.ndarray) -> np.ndarray:
        """Distance [mm] along each unit ray ``(n, 3)`` in B to the cylinder; inf on a miss."""
        T_C_B = self._T_C_B
        o = origins_B @ T_C_B[:3, :3].T + T_C_B[:3, 3]
        d = dirs_B @ T_C_B[:3, :3].T
        r2 = self.radius_mm**2
        n = o.shape[0]
        t_enter = np.zeros(n)
        t_exit = np.full(n, np.inf)
        # Slab along the axis.
        dz = d[:, 2]
        axial = np.abs(dz) > _EPS
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = np.where(axial, (0.0 - o[:, 2]) / dz, -np.inf)
            t1 = np.where(axial, (self.length_mm - o[:, 2]) / dz, np.inf)
        t_enter = np.maximum(t_enter, np.minimum(t0, t1))
        t_exit = np.minimum(t_exit, np.maximum(t0, t1))
        outside_slab = ~axial & ((o[:, 2] < 0.0) | (o[:, 2] > self.length_mm))
        # Infinite circular cylinder x^2 + y^2 = r^2.
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = 2.0 * (o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1])
        c = o[:, 0] ** 2 + o[:, 1] ** 2 - r2
        radial = a > _EPS
        disc = b * b - 4.0 * a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            sq = np.sqrt(np.maximum(disc, 0.0))
            r0 = np.where(radial, (-b - sq) / (2.0 * a), -np.inf)
            r1 = np.where(radial, (-b + sq) / (2.0 * a), np.inf)
        miss_radial = (radial & (disc < 0.0)) | (~radial & (c > 0.0))
        t_enter = np.maximum(t_enter, r0)
        t_exit = np.minimum(t_exit, r1)
        hit = (t_enter <= t_exit) & ~miss_radial & ~outside_slab
        return np.where(hit, t_enter, np.inf)


def nozzle_occluder(T_B_N: np.ndarray, cell: CellConfig) -> CylinderOccluder:
    """The nozzle body: ``cell.nozzle_body_diameter_mm`` wide, ``cell.nozzle_length_mm`` long,
    running from the exit against the spray direction (along -z_N)."""
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # +z_C = -z_N, same origin
    return CylinderOccluder(np.asarray(T_B_N, dtype=np.float64) @ flip,
                            cell.nozzle_body_diameter_mm / 2.0, cell.nozzle_length_mm, "nozzle")

