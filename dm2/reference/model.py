"""Near-net reference: the paper's Gaussian deposition integrated along the executed toolpath.

The reference is a height map ``z_O = h(x, y)`` over the plate (frame ``O``), grown by an
analytic Gaussian footprint at every robot state (paper eq. 1). For a spot with unit spray axis
``a_O`` (nozzle -> surface) the flux per unit area normal to the axis is

    q(r) = V_dot * zeta(theta) / (2 pi sigma^2) * exp(-|r_perp|^2 / (2 sigma^2))   [mm/s]

with ``V_dot = feed / density`` the powder volume rate [mm^3/s], ``r_perp`` the offset from the
impact point perpendicular to the axis and ``theta`` the spray angle between ``-a_O`` and the
reference's own surface normal *at each footprint cell* (a central difference over +-0.5 mm;
with ``angle_from_surface=False`` the build direction ``+z_O`` everywhere, the flat-plate
model). Thickness per horizontal area is ``q * |a_z|`` on a flat cell, added along +z_O. A
tilted spray is followed along its rays: a cell's ``r_perp`` is that of its own surface point
(a cell ``dz`` below the impact point catches the rays ``dz * tan(tilt)`` farther down the tilt),
and its sloped patch catches ``q * |n . a| / n_z`` per horizontal area, so the footprint keeps
its volume on any surface the rays reach once (a tilted contour along a rim or over a mound:
taken on a flat plate at the impact height, the reference put 0.3-0.5 mm too little on the
mound a slow, tilted hole contour builds; occlusion of one part of the surface by another is
not modelled).
For a straight pass on a flat plate at speed ``v`` the peak height is
``V_dot * zeta / (sqrt(2 pi) * sigma * v)``.

The impact point is where the spray axis, ray-marched from the nozzle exit, meets the
reference's own surface: a tilted edge spray over a surface that lags the programmed layer
lands ``dz * tan(tilt)`` further out. Both matter on a part narrower than a few plume widths
(a 30 mm tower grows into a mound whose flanks stick at large spray angles): with the angle
taken from ``+z_O`` the reference kept building the flanks at full efficiency and ran up to
5 mm above the true edge by layer 20, which the monitor called underbuild.

Model choices (documented, deliberately simple, independent of the twin's physics):

* ``zeta(theta) = zeta_0 * cos^2(pi/2 * (theta / theta_c)^2)`` below the critical angle
  ``theta_c = process.critical_angle_deg``, 0 beyond: flat near normal impact as measured
  deposition-efficiency curves are (zeta(15 deg) = 0.98 zeta_0 at 75 deg), zeta(60 deg) =
  0.29 zeta_0, to 0 at ``theta_c``. (A falloff linear in ``cos theta`` already lost 2-4 % on
  the gentle slopes between raster lines once the angle is taken per cell, and left the
  reference 0.3 mm low on a plain pad.) A cell whose curve falls off sooner is described by
  ``process.efficiency_cos_exponent`` ``p``: the curve times ``cos(theta)^p`` (0 by default;
  fitted from a fault-free recording, :mod:`dm2.pipeline.curve_fit`).
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

from dm2.core.frames import invert
from dm2.core.messages import Calibration, LayerMark, RobotState, Toolpath
from dm2.core.plume import plume_sigma_mm
from dm2.fusion.layers import LayerTracker
from dm2.reference import kernels as RK
from dm2.reference.height_map import ReferenceMap
from dm2.reference.plume_width import rescale_plume

log = logging.getLogger(__name__)

KEEP_LAYERS = 8  # finished layers' references kept in ``layers`` (a tall build: not all)
FOOTPRINT_SIGMAS = 4.0  # footprint truncated at 4 sigma (0.03 % of the mass is left out)
SLOPE_PROBE_MM = 0.5  # half span of the central difference giving the local surface normal
MAX_INTEGRATION_GAP_S = 1.0  # longer gaps between robot states are not integrated
MAX_PIECE_S = 0.1  # a dwell deposits at least every 0.1 s (pieces are sigma / 4 long)


def volume_rate_mm3_s(process) -> float:
    """Powder volume rate ``feed / density`` [mm^3/s] (g/min and g/cm^3 in the config)."""
    return process.feed_g_min / 60.0 / (process.powder_density_g_cm3 * 1e-3)


def deposition_efficiency(theta_rad, process) -> np.ndarray:
    """``zeta(theta)``: efficiency at spray angle ``theta`` [rad] from the surface normal."""
    x = np.asarray(theta_rad, dtype=np.float64) / math.radians(process.critical_angle_deg)
    z = process.deposition_efficiency * np.cos(0.5 * np.pi * np.clip(x, 0.0, 1.0) ** 2) ** 2
    z = z * np.abs(np.cos(theta_rad)) ** process.efficiency_cos_exponent
    return np.where(x < 1.0, z, 0.0)


class NearNetReference:
    """Grow the near-net reference from robot states, layer by layer.

    Parameters
    ----------
    process : dm2.core.config.ProcessConfig, nominal process (feed, density, efficiency, plume)
    monitor_cfg : dm2.core.config.MonitorConfig (``voxel_mm`` sets the default grid: half a voxel)
    calibration : dm2.core.messages.Calibration, gives ``T_F_O`` and ``T_B_N``
    size_mm : (2,) plate extent ``(Lx, Ly)`` [mm]
    cell_mm : float [mm], height-map cell (default ``min(0.5, voxel_mm / 2)``)
    angle_from_surface : bool, spray angle against the reference's own local normal
        or (default) against the build direction ``+z_O``
    toolpath : dm2.core.messages.Toolpath or None, splits layers when the stream has no layer marks
    """

    def __init__(self, process, monitor_cfg, calibration: Calibration, *,
                 size_mm=(120.0, 120.0), cell_mm: float | None = None,
                 angle_from_surface: bool = True, toolpath: Toolpath | None = None):
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
        self._v_dot_nominal_mm3_s = self.v_dot_mm3_s
        self.process_scale = 1.0
        self._theta_c = math.radians(process.critical_angle_deg)
        self._T_O_F = invert(calibration.T_F_O)
        self._T_F_O_for_spot = invert(self._T_O_F)  # T_F_O as spot_O always composed it
        T_B_N = calibration.T_B_N
        self._spot_B = T_B_N[:3, :3] @ np.array([0.0, 0.0, process.standoff_mm]) + T_B_N[:3, 3]
        self._axis_B = T_B_N[:3, 2].copy()
        self._T_F_O = np.ascontiguousarray(calibration.T_F_O, dtype=np.float64)
        self._last = np.zeros(16)  # newest state and the pending piece (reference_kernels)
        self._zmax = np.zeros(1)
        self._lut = RK.efficiency_table(process.deposition_efficiency, self._theta_c,
                                        cos_exponent=process.efficiency_cos_exponent)
        self._deposited_mm3 = 0.0
        self._buf_spot = np.empty((64, 3))
        self._buf_axis = np.empty((64, 3))
        self._scratch = np.empty(0)
        self._size_scratch()
        self.stamp_s = 0.0
        self.layers: dict[int, ReferenceMap] = {}
        self.gaps_skipped = 0
        self.angle_from_surface = bool(angle_from_surface)
        self._layer_tracker = LayerTracker(toolpath)
        self.layer = self._layer_tracker.layer
        self.slope_probe_mm = max(SLOPE_PROBE_MM, self.cell_mm)
        self._slope_cells = (max(int(round(self.slope_probe_mm / self.cell_mm)), 1)
                             if self.angle_from_surface else 0)

    @property
    def plume_sigma_mm(self) -> float:
        """The plume width [mm] the model deposits with now (as :class:`ReferenceMap` names it:
        the real-time comparison reads it for its plume term)."""
        return self.sigma_mm

    def set_process_scale(self, scale: float, rescale_deposited: float = 1.0,
                          analysed_to: int | None = None) -> None:
        """Deposit at ``scale`` times the nominal volume rate from now on (efficiency x feed
        against nominal; dm2.process.process_fit), and scale what was deposited so far by
        ``rescale_deposited`` (the first layer's calibration), with the finished layers' maps
        in ``layers`` after ``analysed_to`` (not analysed yet); the others keep the heights
        they were analysed against."""
        if not 0 < scale < 10 or not 0 < rescale_deposited < 10:
            raise ValueError(f"NearNetReference: process scale {scale} and rescale "
                             f"{rescale_deposited} must be in (0, 10)")
        self.process_scale = float(scale)
        self.v_dot_mm3_s = self._v_dot_nominal_mm3_s * self.process_scale
        if rescale_deposited != 1.0:
            self.heights_mm *= rescale_deposited
            self._zmax *= rescale_deposited
            self._deposited_mm3 *= rescale_deposited
            for k, m in list(self.layers.items()):
                if analysed_to is not None and k > analysed_to:
                    self.layers[k] = ReferenceMap(m.heights_mm * rescale_deposited, m.cell_mm,
                                                  m.layer, m.stamp_s, m.plume_sigma_mm)

    def _size_scratch(self) -> None:
        ny, nx = self.heights_mm.shape
        side = 2.0 * FOOTPRINT_SIGMAS * self.sigma_mm / 0.2 / self.cell_mm + 3
        need = int(min(side, nx + 1) * min(side, ny + 1)) + nx + ny + 2
        if self._scratch.size < need:
            self._scratch = np.empty(need)

    def set_plume_factor(self, factor: float) -> None:
        """Deposit with a plume ``factor`` times as wide from now on and widen (or narrow) what
        was deposited so far to match (:mod:`dm2.reference.plume_width`; dm2.pipeline.
        process_fit's plume calibration)."""
        if not 0.5 <= factor <= 2.0:
            raise ValueError(f"NearNetReference: plume factor must be in [0.5, 2], got {factor}")
        if factor == 1.0:
            return
        rescale_plume(self.heights_mm, self.cell_mm, self.sigma_mm, factor)
        self.heights_written()
        self.sigma_mm = self.sigma_mm * factor
        self._size_scratch()

    def heights_written(self) -> None:
        """Call after writing ``heights_mm`` in place (a surface to start from, a test): the
        kernels bound their search for the surface and for a tilted spray's footprint by the
        map's highest value, which the model keeps up to date as it deposits, scales and
        blurs, but cannot see a direct write."""
        self._zmax[0] = float(self.heights_mm.max())

    def spot_O(self, T_B_F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Deposition spot and spray axis in ``O`` for flange poses ``T_B_F`` (..., 4, 4)."""
        T_B_O = np.asarray(T_B_F) @ self._T_F_O_for_spot  # (frames.invert's arithmetic, unchecked:
        R_O_B = np.swapaxes(T_B_O[..., :3, :3], -1, -2)  # these are the feed's own rigid poses)
        t_O_B = -np.einsum("...ij,...j->...i", R_O_B, T_B_O[..., :3, 3])
        spot = np.einsum("...ij,j->...i", R_O_B, self._spot_B) + t_O_B
        axis = np.einsum("...ij,j->...i", R_O_B, self._axis_B)
        return spot, axis

    def feed(self, msg) -> ReferenceMap | None:
        """Take a pipeline message; returns the finished layer's map when a layer ends.

        Layers end on a ``LayerMark``, or, without marks and with a toolpath, when the spot
        reaches the next layer's toolpath (as dm2.fusion.layers decides for the measurement).
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

    def add_states(self, stamps_s, T_B_F, spray_on=None, *, checked: bool = False) -> float:
        """Integrate the deposition up to each robot state; returns the volume added [mm^3].

        Parameters
        ----------
        stamps_s : (m,) float64 [s], increasing
        T_B_F : (m, 4, 4) float64, flange poses
        spray_on : (m,) bool or None, powder flowing on the move into each state (default on)
        checked : the caller (dm2.reference.feed) hands float64 arrays of matching length,
            stamps increasing past the last state's: the checks are skipped
        """
        if checked:
            stamps, T = stamps_s, T_B_F
            on = np.ones(stamps.size, bool) if spray_on is None else spray_on
        else:
            stamps, T, on = self._checked_states(stamps_s, T_B_F, spray_on)
            if stamps.size == 0:
                return 0.0
        if self._buf_spot.shape[0] < stamps.size:
            self._buf_spot = np.empty((stamps.size, 3))
            self._buf_axis = np.empty((stamps.size, 3))
        hm = RK.HeightMap(self.heights_mm, self.cell_mm, self._zmax, self._scratch)
        vol, gaps = RK.integrate_states(
            hm, stamps, T, on, self._T_F_O, self._spot_B, self._axis_B, self._last,
            self._buf_spot, self._buf_axis, self._spray(), MAX_INTEGRATION_GAP_S, MAX_PIECE_S)
        self.stamp_s = float(stamps[-1])
        self.gaps_skipped += int(gaps)
        self._deposited_mm3 += vol
        return float(vol)

    def _checked_states(self, stamps_s, T_B_F, spray_on):
        """``(stamps (m,), poses (m, 4, 4), spray_on (m,))`` as float64 / bool arrays, or a
        ValueError naming what is wrong."""
        stamps = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
        T = np.asarray(T_B_F, dtype=np.float64).reshape(-1, 4, 4)
        if stamps.shape[0] != T.shape[0]:
            raise ValueError(f"add_states: {stamps.shape[0]} stamps but {T.shape[0]} poses")
        on = np.ones(stamps.size, bool) if spray_on is None else np.asarray(spray_on, bool)
        if on.shape != stamps.shape:
            raise ValueError(f"add_states: spray_on must be ({stamps.size},), got {on.shape}")
        if stamps.size and (np.any(np.diff(stamps) < 0)
                            or (self._last[0] > 0 and stamps[0] < self._last[1])):
            raise ValueError("add_states: robot state stamps must not go backwards")
        return stamps, T, on

    def _with_pending(self) -> tuple[np.ndarray, float]:
        """A copy of the map with the pending piece deposited, and that piece's volume.

        The live map (``heights_mm``) lags the newest state by at most one piece (sigma / 4
        of travel); snapshots include it without touching the live map, so the reference
        does not depend on when they are taken.
        """
        h = self.heights_mm.copy()
        hm = RK.HeightMap(h, self.cell_mm, self._zmax.copy(), self._scratch)
        vol = RK.flush_pending(hm, self._last.copy(), self._spray())
        return h, float(vol)

    def _spray(self) -> RK.Spray:
        """The deposition model as the kernels take it (the rate follows the process fit)."""
        return RK.Spray(self.v_dot_mm3_s, self.process.deposition_efficiency, self._theta_c,
                        self.sigma_mm, FOOTPRINT_SIGMAS, self._slope_cells,
                        self.process.standoff_mm, self._lut)

    @property
    def deposited_mm3(self) -> float:
        """Volume deposited up to the newest robot state [mm^3]."""
        return self._deposited_mm3 + self._with_pending()[1]

    def snapshot(self, layer: int | None = None) -> ReferenceMap:
        """The reference as of the last robot state (any time, not only at layer ends)."""
        return ReferenceMap(self._with_pending()[0], self.cell_mm,
                            self.layer if layer is None else layer, self.stamp_s,
                            self.sigma_mm)

    def end_layer(self, layer: int | None = None) -> ReferenceMap:
        """Store and return the reference at the end of ``layer`` (default: the current one)."""
        layer = self.layer if layer is None else int(layer)
        ref = self.snapshot(layer)
        self.layers[layer] = ref
        for old in [k for k in self.layers if k < layer - KEEP_LAYERS]:
            del self.layers[old]  # the analysis has long taken it (and keeps its own)
        log.debug("reference layer %d: %.1f mm^3 so far, max height %.3f mm", layer,
                  self._deposited_mm3, float(ref.heights_mm.max()))
        return ref
