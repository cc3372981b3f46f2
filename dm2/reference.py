"""Near-net reference: the paper's Gaussian deposition integrated along the executed toolpath.

The reference is a height map ``z_O = h(x, y)`` over the plate (frame ``O``), grown by an
analytic Gaussian footprint at every robot state (paper eq. 1). For a spot with unit spray axis
``a_O`` (nozzle -> surface) the flux per unit area normal to the axis is

    q(r) = V_dot * zeta(theta) / (2 pi sigma^2) * exp(-|r_perp|^2 / (2 sigma^2))   [mm/s]

with ``V_dot = feed / density`` the powder volume rate [mm^3/s], ``r_perp`` the offset from the
impact point perpendicular to the axis and ``theta`` the spray angle between ``-a_O`` and the
build direction ``+z_O`` (the layer's nominal surface normal; with ``angle_from_surface=True``
the reference's own local normal, a central difference over +-0.5 mm). Thickness per horizontal
area is ``q * |a_z|`` (mass conserving), added along +z_O. For a straight pass at speed ``v``
the peak height is ``V_dot * zeta / (sqrt(2 pi) * sigma * v)``.

Model choices (documented, deliberately simple, independent of the twin's physics):

* ``zeta(theta) = zeta_0 * max(0, (cos theta - cos theta_c) / (1 - cos theta_c))``: a
  cosine-based falloff from ``process.deposition_efficiency`` at normal impact to 0 at
  ``process.critical_angle_deg``.
* ``sigma`` is ``process.plume_sigma_mm`` when given, else half the plume radius at the
  standoff, the plume widening from the nozzle exit with the half angle
  ``process.plume_half_angle_deg``: ``sigma = (nozzle_exit_mm / 2 + standoff_mm * tan(a)) / 2``
  (6.55 mm exit, 30 mm standoff, 5 deg: 2.95 mm).
* The powder feed is on whenever robot states arrive (cold spray keeps powder flowing through a
  layer); callers that know better pass ``spray_on``.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit

from dm2.frames import invert
from dm2.layers import LayerTracker
from dm2.messages import Calibration, LayerMark, RobotState, Toolpath
from dm2.refmap import ReferenceMap

log = logging.getLogger(__name__)

PLUME_HALF_ANGLE_DEG = 5.0  # used when the process config has no plume_half_angle_deg
FOOTPRINT_SIGMAS = 4.0  # footprint truncated at 4 sigma (0.03 % of the mass is left out)
SLOPE_PROBE_MM = 0.5  # half span of the central difference giving the local surface normal
MAX_INTEGRATION_GAP_S = 1.0  # longer gaps between robot states are not integrated


def plume_sigma_mm(process) -> float:
    """Standard deviation of the Gaussian footprint [mm] (see module docstring)."""
    if process.plume_sigma_mm is not None:
        return float(process.plume_sigma_mm)
    half_angle = getattr(process, "plume_half_angle_deg", PLUME_HALF_ANGLE_DEG)
    radius = 0.5 * process.nozzle_exit_mm + process.standoff_mm * math.tan(
        math.radians(half_angle))
    return 0.5 * radius


def volume_rate_mm3_s(process) -> float:
    """Powder volume rate ``feed / density`` [mm^3/s] (g/min and g/cm^3 in the config)."""
    return process.feed_g_min / 60.0 / (process.powder_density_g_cm3 * 1e-3)


def deposition_efficiency(theta_rad, process) -> np.ndarray:
    """``zeta(theta)``: efficiency at spray angle ``theta`` [rad] from the surface normal."""
    cos_c = math.cos(math.radians(process.critical_angle_deg))
    c = np.cos(np.asarray(theta_rad, dtype=np.float64))
    return process.deposition_efficiency * np.clip((c - cos_c) / (1.0 - cos_c), 0.0, 1.0)


@njit(cache=True)
def _bilinear(h, cell, x, y):
    ny, nx = h.shape
    fx = min(max(x / cell - 0.5, 0.0), nx - 1.0)
    fy = min(max(y / cell - 0.5, 0.0), ny - 1.0)
    i0 = min(int(fx), nx - 2) if nx > 1 else 0
    j0 = min(int(fy), ny - 2) if ny > 1 else 0
    tx = fx - i0
    ty = fy - j0
    i1 = min(i0 + 1, nx - 1)
    j1 = min(j0 + 1, ny - 1)
    return ((1 - tx) * (1 - ty) * h[j0, i0] + tx * (1 - ty) * h[j0, i1]
            + (1 - tx) * ty * h[j1, i0] + tx * ty * h[j1, i1])


@njit(cache=True)
def _deposit_spots(h, cell, spots, axes, dts, v_dot, zeta0, cos_c, sigma, n_sigma,
                   slope_probe):
    """Add the Gaussian footprint of each spot, in order, to ``h`` (mutated). Returns volume."""
    ny, nx = h.shape
    total = 0.0
    inv2s2 = 1.0 / (2.0 * sigma * sigma)
    for k in range(spots.shape[0]):
        ax, ay, az = axes[k, 0], axes[k, 1], axes[k, 2]
        px, py, pz = spots[k, 0], spots[k, 1], spots[k, 2]
        if az < -1e-6:  # slide the spot along the axis onto the current reference surface
            for _ in range(2):
                t = (_bilinear(h, cell, px, py) - pz) / az
                px += t * ax
                py += t * ay
                pz += t * az
        if slope_probe > 0.0:  # spray angle against the local reference surface normal
            gx = (_bilinear(h, cell, px + slope_probe, py)
                  - _bilinear(h, cell, px - slope_probe, py)) / (2 * slope_probe)
            gy = (_bilinear(h, cell, px, py + slope_probe)
                  - _bilinear(h, cell, px, py - slope_probe)) / (2 * slope_probe)
            cos_t = (ax * gx + ay * gy - az) / math.sqrt(gx * gx + gy * gy + 1.0)
        else:  # spray angle from the build direction +z_O
            cos_t = -az
        zeta = zeta0 * min(max((cos_t - cos_c) / (1.0 - cos_c), 0.0), 1.0)
        if zeta <= 0.0 or dts[k] <= 0.0:
            continue
        amp = v_dot * zeta * dts[k] / (2.0 * math.pi * sigma * sigma) * abs(az)
        reach = n_sigma * sigma / max(abs(az), 0.2)
        i_lo = max(int((px - reach) / cell), 0)
        i_hi = min(int((px + reach) / cell) + 1, nx - 1)
        j_lo = max(int((py - reach) / cell), 0)
        j_hi = min(int((py + reach) / cell) + 1, ny - 1)
        lim2 = (n_sigma * sigma) ** 2
        for j in range(j_lo, j_hi + 1):
            ry = (j + 0.5) * cell - py
            for i in range(i_lo, i_hi + 1):
                rx = (i + 0.5) * cell - px
                along = rx * ax + ry * ay
                d2 = rx * rx + ry * ry - along * along
                if d2 > lim2:
                    continue
                dz = amp * math.exp(-d2 * inv2s2)
                h[j, i] += dz
                total += dz * cell * cell
    return total


class NearNetReference:
    """Grow the near-net reference from robot states, layer by layer.

    Parameters
    ----------
    process : dm2.config.ProcessConfig, nominal process (feed, density, efficiency, plume)
    monitor_cfg : dm2.config.MonitorConfig (``voxel_mm`` sets the default grid: half a voxel)
    calibration : dm2.messages.Calibration, gives ``T_F_O`` and ``T_B_N``
    size_mm : (2,) plate extent ``(Lx, Ly)`` [mm]
    cell_mm : float [mm], height-map cell (default ``min(0.5, voxel_mm / 2)``)
    angle_from_surface : bool, spray angle against the reference's own local normal
        or (default) against the build direction ``+z_O``
    toolpath : dm2.messages.Toolpath or None, splits layers when the stream has no layer marks
    """

    def __init__(self, process, monitor_cfg, calibration: Calibration, *,
                 size_mm=(120.0, 120.0), cell_mm: float | None = None,
                 angle_from_surface: bool = False, toolpath: Toolpath | None = None):
        self.process = process
        self.cell_mm = float(cell_mm if cell_mm is not None else min(0.5, monitor_cfg.voxel_mm / 2))
        if self.cell_mm <= 0:
            raise ValueError(f"NearNetReference: cell_mm must be positive, got {self.cell_mm}")
        self.size_mm = (float(size_mm[0]), float(size_mm[1]))
        nx = max(int(round(self.size_mm[0] / self.cell_mm)), 2)
        ny = max(int(round(self.size_mm[1] / self.cell_mm)), 2)
        self.heights_mm = np.zeros((ny, nx))
        self.sigma_mm = plume_sigma_mm(process)
        self.v_dot_mm3_s = volume_rate_mm3_s(process)
        self._cos_c = math.cos(math.radians(process.critical_angle_deg))
        self._T_O_F = invert(calibration.T_F_O)
        T_B_N = calibration.T_B_N
        self._spot_B = T_B_N[:3, :3] @ np.array([0.0, 0.0, process.standoff_mm]) + T_B_N[:3, 3]
        self._axis_B = T_B_N[:3, 2].copy()
        self._last: tuple[float, np.ndarray, np.ndarray] | None = None
        self.stamp_s = 0.0
        self.layers: dict[int, ReferenceMap] = {}
        self.deposited_mm3 = 0.0
        self.gaps_skipped = 0
        self.angle_from_surface = bool(angle_from_surface)
        self._layer_tracker = LayerTracker(toolpath)
        self.layer = self._layer_tracker.layer
        self.slope_probe_mm = max(SLOPE_PROBE_MM, self.cell_mm)

    def spot_O(self, T_B_F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Deposition spot and spray axis in ``O`` for flange poses ``T_B_F`` (..., 4, 4)."""
        T_O_B = invert(np.asarray(T_B_F) @ invert(self._T_O_F))  # inv(T_B_F @ T_F_O)
        spot = np.einsum("...ij,j->...i", T_O_B[..., :3, :3], self._spot_B) + T_O_B[..., :3, 3]
        axis = np.einsum("...ij,j->...i", T_O_B[..., :3, :3], self._axis_B)
        return spot, axis

    def feed(self, msg) -> ReferenceMap | None:
        """Take a pipeline message; returns the finished layer's map when a layer ends.

        Layers end on a ``LayerMark``, or, without marks and with a toolpath, when the spot
        reaches the next layer's toolpath (as dm2.layers decides for the measurement).
        """
        finished: list[int] = []
        if isinstance(msg, RobotState):
            if self._layer_tracker.source == "toolpath":
                finished = self._layer_tracker.on_spots(self.spot_O(msg.T_B_F[None])[0])
            done = [self.end_layer(f) for f in finished]
            self.layer = self._layer_tracker.layer
            self.add_states([msg.stamp_s], msg.T_B_F[None])
            return done[-1] if done else None
        if isinstance(msg, LayerMark):
            f = self._layer_tracker.on_mark(msg.layer)
            if f is not None:
                done = self.end_layer(f)
                self.layer = self._layer_tracker.layer
                return done
        return None

    def add_states(self, stamps_s, T_B_F, spray_on=None) -> float:
        """Integrate the deposition up to each robot state; returns the volume added [mm^3].

        Parameters
        ----------
        stamps_s : (m,) float64 [s], increasing
        T_B_F : (m, 4, 4) float64, flange poses
        spray_on : (m,) bool or None, powder flowing on the move into each state (default on)
        """
        stamps = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
        T = np.asarray(T_B_F, dtype=np.float64).reshape(-1, 4, 4)
        if stamps.shape[0] != T.shape[0]:
            raise ValueError(f"add_states: {stamps.shape[0]} stamps but {T.shape[0]} poses")
        if stamps.size == 0:
            return 0.0
        on = np.ones(stamps.size, bool) if spray_on is None else np.asarray(spray_on, bool)
        spot, axis = self.spot_O(T)
        if self._last is not None:
            stamps = np.concatenate([[self._last[0]], stamps])
            spot = np.vstack([self._last[1], spot])
            axis = np.vstack([self._last[2], axis])
            on = np.concatenate([[False], on])
        self._last = (float(stamps[-1]), spot[-1].copy(), axis[-1].copy())
        self.stamp_s = float(stamps[-1])
        dt = np.diff(stamps)
        if np.any(dt < 0):
            raise ValueError("add_states: robot state stamps must not go backwards")
        gap = dt > MAX_INTEGRATION_GAP_S
        self.gaps_skipped += int(gap.sum())
        use = on[1:] & ~gap & (dt > 0)
        if not np.any(use):
            return 0.0
        sub_spots, sub_axes, sub_dt = self._subsample(spot[:-1][use], spot[1:][use],
                                                      axis[:-1][use], axis[1:][use], dt[use])
        vol = _deposit_spots(self.heights_mm, self.cell_mm, sub_spots, sub_axes, sub_dt,
                             self.v_dot_mm3_s, self.process.deposition_efficiency, self._cos_c,
                             self.sigma_mm, FOOTPRINT_SIGMAS,
                             self.slope_probe_mm if self.angle_from_surface else 0.0)
        self.deposited_mm3 += vol
        return float(vol)

    def _subsample(self, p0, p1, a0, a1, dt):
        """Split each move into pieces no longer than sigma / 4; spots at the piece midpoints."""
        length = np.linalg.norm(p1 - p0, axis=1)
        n = np.maximum(np.ceil(length / (self.sigma_mm / 4.0)).astype(np.int64), 1)
        idx = np.repeat(np.arange(len(n)), n)
        start = np.cumsum(n) - n
        frac = (np.arange(idx.size) - start[idx] + 0.5) / n[idx]
        spots = p0[idx] + (p1[idx] - p0[idx]) * frac[:, None]
        axes = a0[idx] + (a1[idx] - a0[idx]) * frac[:, None]
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        return (np.ascontiguousarray(spots), np.ascontiguousarray(axes),
                np.ascontiguousarray((dt / n)[idx]))

    def snapshot(self, layer: int | None = None) -> ReferenceMap:
        """The reference as of the last robot state (any time, not only at layer ends)."""
        return ReferenceMap(self.heights_mm.copy(), self.cell_mm,
                            self.layer if layer is None else layer, self.stamp_s)

    def end_layer(self, layer: int | None = None) -> ReferenceMap:
        """Store and return the reference at the end of ``layer`` (default: the current one)."""
        layer = self.layer if layer is None else int(layer)
        ref = self.snapshot(layer)
        self.layers[layer] = ref
        log.debug("reference layer %d: %.1f mm^3 so far, max height %.3f mm", layer,
                  self.deposited_mm3, float(ref.heights_mm.max()))
        return ref
