"""Analytic occluders for the virtual profilers: solids that block rays but are never measured.

The deposit and the plate are ray-cast on the height field; occluders such as the nozzle body
are closed-form ray/solid intersections in the robot base B, vectorised over rays. Every
``hit_t`` returns the distance [mm] along unit directions to the first entry into the solid
(``np.inf`` where the ray misses it); a ray that starts inside a solid is blocked at ``t = 0``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from dm2.core.frames import invert
from dm2.core.tolerances import NEAR_ZERO
from twin.schema import CellConfig


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
        o = np.ascontiguousarray(origins_B @ T_C_B[:3, :3].T + T_C_B[:3, 3], dtype=np.float64)
        d = np.ascontiguousarray(dirs_B @ T_C_B[:3, :3].T, dtype=np.float64)
        out = np.empty(o.shape[0], dtype=np.float64)
        _cylinder_hit_t(o, d, float(self.radius_mm**2), float(self.length_mm), out)
        return out

    def blocks(self, T_B_X: np.ndarray, starts_X: np.ndarray, dirs_X: np.ndarray,
               reach_mm: np.ndarray, out: np.ndarray) -> None:
        """Mark ``out (n,)`` True where a unit ray ``(n, 3)`` given in frame X (posed by
        ``T_B_X``) enters the cylinder within ``reach_mm (n,)``; already True stays True.

        The same test as ``hit_t(...) < reach_mm`` in one pass, without the intermediate
        arrays (last-bit differences of the entry distance could only matter for a ray that
        meets the cylinder exactly at its reach).
        """
        cylinder_blocks(np.ascontiguousarray(self._T_C_B @ T_B_X), float(self.radius_mm**2),
                        float(self.length_mm), starts_X, dirs_X, reach_mm, out)


@njit(cache=True)
def _cylinder_entry(ox, oy, oz, dx, dy, dz, r2, length):
    """Entry distance of the ray ``o + t d`` (in the cylinder frame) into the solid cylinder
    ``x^2 + y^2 <= r2, 0 <= z <= length``; inf on a miss, 0 for a ray starting inside."""
    t_enter = 0.0
    t_exit = np.inf
    # slab along the axis
    if abs(dz) > NEAR_ZERO:
        t0 = (0.0 - oz) / dz
        t1 = (length - oz) / dz
        t_enter = max(t_enter, min(t0, t1))
        t_exit = min(t_exit, max(t0, t1))
    elif oz < 0.0 or oz > length:
        return np.inf
    # infinite circular cylinder x^2 + y^2 = r^2
    a = dx * dx + dy * dy
    b = 2.0 * (ox * dx + oy * dy)
    c = ox * ox + oy * oy - r2
    if a > NEAR_ZERO:
        disc = b * b - 4.0 * a * c
        if disc < 0.0:
            return np.inf
        sq = np.sqrt(disc)
        t_enter = max(t_enter, (-b - sq) / (2.0 * a))
        t_exit = min(t_exit, (-b + sq) / (2.0 * a))
    elif c > 0.0:
        return np.inf
    return t_enter if t_enter <= t_exit else np.inf


@njit(cache=True, nogil=True)
def _cylinder_hit_t(o, d, r2, length, out):
    """:func:`_cylinder_entry` for rays ``o (n, 3)``, ``d (n, 3)`` in the cylinder frame."""
    for k in range(o.shape[0]):
        out[k] = _cylinder_entry(o[k, 0], o[k, 1], o[k, 2], d[k, 0], d[k, 1], d[k, 2], r2,
                                 length)


@njit(cache=True)
def cylinder_blocks_one(T_C_X, r2, length, start, d, reach):
    """Whether the ray ``start (3,) + t d (3,)`` in frame X (posed by ``T_C_X (4, 4)`` in the
    cylinder frame) enters the cylinder before ``reach`` [mm]."""
    sx, sy, sz = start[0], start[1], start[2]
    dx, dy, dz = d[0], d[1], d[2]
    ox = T_C_X[0, 0] * sx + T_C_X[0, 1] * sy + T_C_X[0, 2] * sz + T_C_X[0, 3]
    oy = T_C_X[1, 0] * sx + T_C_X[1, 1] * sy + T_C_X[1, 2] * sz + T_C_X[1, 3]
    oz = T_C_X[2, 0] * sx + T_C_X[2, 1] * sy + T_C_X[2, 2] * sz + T_C_X[2, 3]
    ex = T_C_X[0, 0] * dx + T_C_X[0, 1] * dy + T_C_X[0, 2] * dz
    ey = T_C_X[1, 0] * dx + T_C_X[1, 1] * dy + T_C_X[1, 2] * dz
    ez = T_C_X[2, 0] * dx + T_C_X[2, 1] * dy + T_C_X[2, 2] * dz
    return _cylinder_entry(ox, oy, oz, ex, ey, ez, r2, length) < reach


@njit(cache=True, nogil=True)
def cylinder_blocks(T_C_X, r2, length, starts_X, dirs_X, reach, out):
    """Set ``out[k] = True`` where the ray ``starts_X[k] + t dirs_X[k]`` (frame X, posed by
    ``T_C_X (4, 4)`` in the cylinder frame) enters the cylinder before ``reach[k]`` [mm]."""
    for k in range(starts_X.shape[0]):
        if not out[k]:
            out[k] = cylinder_blocks_one(T_C_X, r2, length, starts_X[k], dirs_X[k], reach[k])


def nozzle_occluder(T_B_N: np.ndarray, cell: CellConfig) -> CylinderOccluder:
    """The nozzle body: ``cell.nozzle_body_diameter_mm`` wide, ``cell.nozzle_length_mm`` long,
    running from the exit against the spray direction (along -z_N)."""
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # +z_C = -z_N, same origin
    return CylinderOccluder(np.asarray(T_B_N, dtype=np.float64) @ flip,
                            cell.nozzle_body_diameter_mm / 2.0, cell.nozzle_length_mm, "nozzle")

