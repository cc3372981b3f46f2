"""Virtual laser-line profilers modelled on a scanCONTROL 29xx (their trigger schedule is in
:mod:`twin.profiler.trigger`).

A profiler emits a fan of ``sensors.points`` rays from the origin of its frame ``S``, in the
x_S-z_S plane, spaced evenly in x at ``z = z_end_mm`` so that the fan is ``x_width_end_mm`` wide
there. A point is valid only when the laser ray reaches the surface inside the measuring range
``[z_start_mm, z_end_mm]`` and the triangulation camera at ``(0, camera_baseline_mm, 0)`` in S
sees the lit spot: both rays are cast on the deposit height field (a ray marcher, so the deposit
may change every step), against the plate's side faces, and against analytic occluders such
as the nozzle body (:mod:`twin.profiler.occluders`). Intensity follows the cosine of the incidence
angle. Noise is applied along each ray (range): Gaussian range noise, spatially correlated
speckle, dropouts and rare multiple-reflection ghosts that appear beyond the surface. The
random stream of a profile is seeded from ``(seed, sensor, counter)``, so a profile does not
depend on the order in which profiles are generated. Invalid points carry ``valid = False``
and NaN coordinates, as the real sensor reports them.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from dm2.core.config import SensorConfig
from dm2.core.messages import COUNTER_MODULO, SENSOR_IDS, Profile
from twin.profiler import noise_kernels as PN
from twin.profiler import scan_kernels as PS
from twin.profiler.artefacts import ProfileArtefacts
from twin.profiler.kernels import PlateField
from twin.profiler.model import _FACE_TOL_MM, _LIFT_MM, ProfileTrace, first_occluder_hit
from twin.profiler.occluders import CylinderOccluder
from twin.schema import NoiseConfig
from twin.world.heightfield import HeightField

log = logging.getLogger(__name__)

def fan_directions_S(sensors: SensorConfig) -> np.ndarray:
    """Unit laser-ray directions ``(points, 3)`` in S, ordered by increasing x_S."""
    half = sensors.x_width_end_mm / 2.0
    x = np.linspace(-half, half, sensors.points)
    d = np.column_stack([x, np.zeros_like(x), np.full_like(x, sensors.z_end_mm)])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


class VirtualProfiler:
    """One laser profiler fixed in the cell.

    Parameters
    ----------
    sensor_id : one of ``SENSOR_IDS``
    T_B_S : (4, 4) float64, the profiler's true pose in the robot base [mm]
    sensors, noise : the scenario's ``[sensors]`` and ``[noise]`` sections
    seed : int, scenario seed; the profile noise stream is ``(seed, sensor, counter)``
    T_B_N : (4, 4) the nozzle in B, where the powder jet crosses the laser sheet (the plume
        particles of :mod:`twin.profiler.artefacts`); None: no particles
    """

    def __init__(self, sensor_id: str, T_B_S: np.ndarray, sensors: SensorConfig,
                 noise: NoiseConfig, seed: int = 0, T_B_N: np.ndarray | None = None):
        if sensor_id not in SENSOR_IDS:
            raise ValueError(f"VirtualProfiler: sensor_id {sensor_id!r} not in {SENSOR_IDS}")
        T = np.asarray(T_B_S, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"VirtualProfiler {sensor_id}: T_B_S must be a finite (4, 4) pose")
        self.sensor_id = sensor_id
        self.sensor_index = SENSOR_IDS.index(sensor_id)
        self.T_B_S = T
        self.sensors = sensors
        self.noise = noise
        self.seed = int(seed) & 0xFFFFFFFFFFFFFFFF
        self.dirs_S = fan_directions_S(sensors)
        self.camera_S = np.array([0.0, sensors.camera_baseline_mm, 0.0])
        self._t_min = sensors.z_start_mm / self.dirs_S[:, 2]
        self._t_max = sensors.z_end_mm / self.dirs_S[:, 2]
        self._max_range_mm = float(self._t_max.max())
        # lit points lie in the measuring trapezoid, so its farthest corner (plus the lift, with
        # margin) bounds every camera ray: one reach per profiler, whatever rays a pass holds
        ends = np.concatenate([self.dirs_S[[0, -1]] * self._t_min[[0, -1], None],
                               self.dirs_S[[0, -1]] * self._t_max[[0, -1], None]])
        self._camera_reach_mm = float(np.linalg.norm(ends - self.camera_S, axis=1).max()
                                      + 2.0 * _LIFT_MM)
        self._dir_x = np.ascontiguousarray(self.dirs_S[:, 0])
        self._dir_z = np.ascontiguousarray(self.dirs_S[:, 2])
        self._occluder_cache = None
        self._kernel_cache = None
        half = int(np.ceil(3.0 * noise.speckle_length_points))
        kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / noise.speckle_length_points) ** 2)
        self._speckle_kernel = kernel / np.sqrt(np.sum(kernel * kernel))
        lo, hi = noise.outlier_offset_mm
        # the kernels' bundles as plain tuples of their fields (see twin.profiler.scan_kernels)
        self._stream = tuple(PN.DrawStream(self.seed, self.sensor_index, self._speckle_kernel,
                                           float(lo), float(hi)))
        self._model = tuple(PN.SensorModel(float(noise.range_sigma_mm),
                                           float(noise.speckle_sigma_mm),
                                           float(noise.outlier_prob), float(noise.dropout_prob),
                                           self._dir_x, self._dir_z, float(sensors.z_start_mm),
                                           float(sensors.z_end_mm)))
        # a cold-spray cell's artefacts (twin.profiler.artefacts), when [noise] asks for one
        T_S_N = None if T_B_N is None else np.linalg.solve(T, np.asarray(T_B_N, np.float64))
        self._artefacts = (ProfileArtefacts(noise, self.seed, self.sensor_index, self.dirs_S,
                                            (sensors.z_start_mm, sensors.z_end_mm), T_S_N)
                           if noise.dirty() else None)

    # ------------------------------------------------------------------ geometry
    def trace(self, hf, T_B_O: np.ndarray, occluders: Sequence | None = None) -> ProfileTrace:
        """Cast the fan on the height field ``hf`` (in O, posed by ``T_B_O``); no noise.

        A :class:`~twin.world.heightfield.HeightField` seen past capped-cylinder occluders is cast
        in
        one call of :func:`twin.profiler.scan_kernels.trace_posed`; any other surface object or
        occluder goes through :meth:`trace_numpy`. Both give the same bits.
        """
        occluders = tuple(occluders or ())
        setup = self._kernel_setup(occluders)
        if not isinstance(hf, HeightField) or setup is None:
            return self.trace_numpy(hf, T_B_O, occluders)
        out = self.empty_trace()
        self.trace_rays(hf, T_B_O, occluders, out, 0, out.range_mm.size)
        return out

    def empty_trace(self) -> ProfileTrace:
        """A :class:`ProfileTrace` of uninitialised arrays for :meth:`trace_rays` to fill."""
        n = self.dirs_S.shape[0]
        return ProfileTrace(np.empty(n), np.empty(n, dtype=np.int8), np.empty(n),
                            np.empty((n, 3)))

    def trace_rays(self, hf: HeightField, T_B_O: np.ndarray, occluders: tuple,
                   out: ProfileTrace, r0: int, r1: int) -> None:
        """Fill the entries ``r0:r1`` of ``out`` (from :meth:`empty_trace`) with
        :meth:`trace` of fan rays ``r0:r1`` (the same bits as one whole trace), so that parts
        of a fan may be cast on different threads. Capped-cylinder occluders only."""
        setup = self._kernel_setup(tuple(occluders))
        if setup is None:
            raise TypeError(f"{self.sensor_id}: trace_rays casts capped-cylinder occluders only")
        PS.trace_posed(_plate_field(hf), setup, np.ascontiguousarray(T_B_O, dtype=np.float64),
                       int(r0), int(r1), out.range_mm, out.reason, out.cos_incidence,
                       out.points_O)

    def _kernel_setup(self, occluders: tuple):
        """The constant inputs of :mod:`twin.profiler.scan_kernels` for this occluder set (a
        :class:`twin.profiler.scan_kernels.Scanner` as a plain tuple of its fields, as the
        kernels take it from Python); None when an occluder is not a
        :class:`~twin.profiler.occluders.CylinderOccluder`. Made once per occluder set."""
        key = tuple(id(o) for o in occluders)
        cached = self._kernel_cache
        if cached is not None and cached[0] == key:
            return cached[2]
        setup = None
        if all(isinstance(o, CylinderOccluder) for o in occluders):
            k = len(occluders)
            t_occ = self._laser_occluder_t(occluders) if occluders else self._t_max
            T_C_B = np.zeros((k, 4, 4))
            r2, length = np.zeros(k), np.zeros(k)
            for i, o in enumerate(occluders):
                T_C_B[i] = o._T_C_B
                r2[i], length[i] = o.radius_mm ** 2, o.length_mm
            f64 = np.float64
            setup = tuple(PS.Scanner(
                np.array(self.dirs_S, dtype=f64), np.array(self._t_min, dtype=f64),
                np.array(self._t_max, dtype=f64), np.array(t_occ, dtype=f64), self.T_B_S,
                self.camera_S, T_C_B, r2, length, bool(occluders), self._max_range_mm,
                float(_FACE_TOL_MM), float(_LIFT_MM), self._camera_reach_mm,
                float(self.noise.min_intensity)))
        # the occluders are held so that their ids stay theirs while cached
        self._kernel_cache = (key, occluders, setup)
        return setup

    def trace_numpy(self, hf, T_B_O: np.ndarray,
                        occluders: Sequence | None = None) -> ProfileTrace:
        """:meth:`trace` in plain numpy (:mod:`twin.profiler.numpy_path`), on any surface."""
        from twin.profiler.numpy_path import trace_numpy

        return trace_numpy(self, hf, T_B_O, occluders)

    def _laser_occluder_t(self, occluders: tuple) -> np.ndarray:
        """Distance (n,) [mm] along each laser ray to the first occluder (inf: none).

        Occluders and the profiler are both fixed in B, so this is cast once per occluder set.
        """
        key = tuple(id(o) for o in occluders)
        cached = self._occluder_cache
        if cached is None or cached[0] != key:
            n = self.dirs_S.shape[0]
            origins_B = np.broadcast_to(self.T_B_S[:3, 3], (n, 3))
            dirs_B = self.dirs_S @ self.T_B_S[:3, :3].T
            t_occ = first_occluder_hit(occluders, origins_B, dirs_B)
            t_occ.setflags(write=False)
            # the occluders are held so that their ids stay theirs while cached
            cached = self._occluder_cache = (key, occluders, t_occ)
        return cached[2]

    # ------------------------------------------------------------------ sensor output
    def scan(self, hf, T_B_O: np.ndarray, stamp_s: float, counter: int,
             occluders: Sequence | None = None, spray: float = 1.0) -> Profile:
        """One profile of ``hf`` with the plate at ``T_B_O``, stamped ``stamp_s``.

        Parameters
        ----------
        hf : twin.world.heightfield.HeightField (anything with ``raycast``, ``height_at``,
            ``size_mm`` and ``thickness_mm``), the true surface in O
        T_B_O : (4, 4) float64, plate pose in the robot base at ``stamp_s`` [mm]
        stamp_s : float [s]; counter : int, the 24-bit profile counter
        occluders : objects with ``hit_t(origins_B, dirs_B) -> t_mm`` (e.g. the nozzle body)
        spray : the feed now over ``[noise] plume_feed_ref_g_min`` (0: spray off), for the
            plume particles
        """
        occluders = tuple(occluders or ())
        setup = self._kernel_setup(occluders)
        if not isinstance(hf, HeightField) or setup is None:
            return self.measure(self.trace(hf, T_B_O, occluders), stamp_s, counter, spray)
        counter = self._check_counter(counter)
        n = self.dirs_S.shape[0]
        xz = np.empty((n, 2))
        valid = np.empty(n, dtype=bool)
        intensity = np.empty(n, dtype=np.float32)
        PS.scan_pass(_plate_field(hf), setup, self._stream, self._model,
                     np.ascontiguousarray(T_B_O, dtype=np.float64), counter, xz, valid,
                     intensity)
        if self._artefacts is not None:
            self._artefacts.apply(xz, valid, intensity, float(stamp_s), counter, spray)
        return Profile.trusted(self.sensor_id, float(stamp_s), counter, xz, valid, intensity)

    def _check_counter(self, counter) -> int:
        counter = int(counter)
        if not 0 <= counter < COUNTER_MODULO:
            raise ValueError(f"{self.sensor_id}: counter {counter} outside the 24-bit range")
        return counter

    def measure(self, trace: ProfileTrace, stamp_s: float, counter: int,
                spray: float = 1.0) -> Profile:
        """Apply the sensor's noise (and artefacts: ``spray`` as for :meth:`scan`) to a trace
        and format it as a :class:`Profile`."""
        counter = self._check_counter(counter)
        n = trace.range_mm.size
        xz = np.empty((n, 2))
        valid = np.empty(n, dtype=bool)
        intensity = np.empty(n, dtype=np.float32)
        PN.measure_pass(self._stream, self._model, counter,
                        np.ascontiguousarray(trace.range_mm, dtype=np.float64),
                        np.ascontiguousarray(trace.reason, dtype=np.int8),
                        np.ascontiguousarray(trace.cos_incidence, dtype=np.float64),
                        xz, valid, intensity)
        if self._artefacts is not None:
            self._artefacts.apply(xz, valid, intensity, float(stamp_s), counter, spray)
        return Profile.trusted(self.sensor_id, float(stamp_s), counter, xz, valid, intensity)

    def _draws(self, counter: int, n: int):
        """The profile's random draws from its ``(seed, sensor, counter)`` stream
        (:func:`twin.profiler.noise_kernels.noise_draws`), in order: range noise, speckle,
        dropout and ghost uniforms, ghost offsets [mm], each ``(n,)``."""
        draws = PN.Draws(*(np.empty(n) for _ in range(5)))
        PN.noise_draws(self._stream, int(counter), tuple(draws))
        return tuple(draws)

    def measure_numpy(self, trace: ProfileTrace, stamp_s: float, counter: int,
                      spray: float = 1.0) -> Profile:
        """:meth:`measure` in plain numpy (:mod:`twin.profiler.numpy_path`)."""
        from twin.profiler.numpy_path import measure_numpy

        return measure_numpy(self, trace, stamp_s, counter, spray)

    def _noise(self, trace: ProfileTrace, counter: int):
        """Noisy ranges, reasons (DROPOUT marked) and intensities, before the measuring range."""
        from twin.profiler.numpy_path import _noise

        return _noise(self, trace, counter)


def _plate_field(hf: HeightField) -> tuple:
    """``hf``'s arrays and plate as the profiler kernels take them from Python (no copies): the
    fields of a :class:`twin.profiler.kernels.PlateField`, as a plain tuple."""
    return tuple(PlateField(hf._h, hf._bmax, hf._zmax, float(hf.cell_mm), float(hf.thickness_mm),
                            float(hf.size_mm[0]), float(hf.size_mm[1])))
