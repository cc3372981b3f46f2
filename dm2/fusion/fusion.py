"""The fusion pipeline: messages in, per-layer surfaces out (paper sections 4-5).

``TsdfFusion.feed(msg)`` takes :class:`~dm2.core.messages.Profile`,
:class:`~dm2.core.messages.RobotState`
and :class:`~dm2.core.messages.LayerMark` messages from any source (twin, recording, live drivers),
in any order within the reorder window. Profiles are synchronised with interpolated poses
(:mod:`dm2.fusion.sync`), registered into ``O`` (:mod:`dm2.fusion.registration`, eq 1), fused into
the sparse
TSDF with adaptive weights around the nozzle's impact point (:mod:`dm2.fusion.tsdf.field`, eqs 2-5)
and, at
each layer's end (:mod:`dm2.fusion.layers`), triangulated (:mod:`dm2.fusion.surface`).
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable, Iterable

import numpy as np

from dm2.core.config import MonitorConfig, ProcessConfig
from dm2.core.messages import Calibration, Toolpath
from dm2.core.plume import plume_sigma_mm
from dm2.fusion.layers import LayerTracker
from dm2.fusion.point_filter import PointFilter
from dm2.fusion.profile_merge import merge_profile_points
from dm2.fusion.registration import profile_frames, register_profile, spot_B
from dm2.fusion.surface import PendingSurface, SurfaceExtractor, SurfaceMesh
from dm2.fusion.sync import StreamSync, SyncedProfile
from dm2.fusion.tsdf.field import SparseTSDF
from dm2.io.spill import SpillStore

log = logging.getLogger(__name__)

# One frame set of the three cascaded sensors per kernel call: what per-frame-set consumers
# (the session's real-time deviation, live latency) need. Offline replays with no such consumer
# may pass REPLAY_BATCH_PROFILES (about 3 s of a 3 x 10 Hz stream per call).
DEFAULT_BATCH_PROFILES = 3
REPLAY_BATCH_PROFILES = 96
DEFAULT_MAX_DELAY_S = 0.02


class LayerSurface:
    """The reconstructed surface when a layer finished.

    Attributes
    ----------
    layer : int, the layer that finished
    stamp_s : float [s], stamp of the last profile fused into it (NaN if none)
    surface : SurfaceMesh in ``O``; when built from a :class:`~dm2.fusion.surface.PendingSurface`
        (``TsdfFusion(defer_meshing=True)``) it is meshed on first access, on that thread
    """

    __slots__ = ("layer", "stamp_s", "_surface")

    def __init__(self, layer: int, stamp_s: float, surface: SurfaceMesh | PendingSurface):
        self.layer = int(layer)
        self.stamp_s = float(stamp_s)
        self._surface = surface

    @property
    def surface(self) -> SurfaceMesh:
        if isinstance(self._surface, PendingSurface):
            self._surface = self._surface.result()
        return self._surface

    def __repr__(self) -> str:
        return f"LayerSurface(layer={self.layer}, stamp_s={self.stamp_s})"


def default_active_radius_mm(process: ProcessConfig) -> float:
    """Two plume sigmas [mm] (the footprint's sigma as the near-net reference models it)."""
    return 2.0 * plume_sigma_mm(process)


class TsdfFusion:
    """In-process reconstruction of the growing part from profiles and robot poses.

    Parameters
    ----------
    calibration : sensor poses ``T_B_S``, work object on the flange ``T_F_O``, nozzle ``T_B_N``
    monitor_cfg : voxel size, truncation, weights, sync limits
    process : standoff (deposition spot) and plume (active radius default)
    toolpath : optional; splits layers when the stream carries no layer marks
    on_layer_done : optional callback ``f(LayerSurface)`` called when a layer finishes
    bounds_O : optional ``(lo (3,), hi (3,))`` [mm]; points outside are dropped as out_of_range
    batch_profiles : synchronised profiles are fused in batches of this many (default 3 = one
        frame set of the three cascaded sensors; ``REPLAY_BATCH_PROFILES`` for offline replays
        that read nothing between frame sets); layer ends, ``surface()`` and ``finish()`` flush
        early. Batching never changes the result: each profile keeps its own
        pose and active region, and profiles are fused in stream order
    max_delay_s : float [s], wall-clock time after which a waiting batch is fused at the next
        message even when not full, so a live stream sees its profiles fused within about this
        long; ``inf`` fuses full batches only, whatever the reading speed (what a replay's
        session passes, dm2.pipeline.session)
    defer_meshing : at a layer end only copy the chunk boxes to re-mesh; the layer's
        surface is meshed where it is first read (a live session's worker thread)

    Attributes
    ----------
    layer_done : list of LayerSurface, finished layers in order (with
        ``monitor_cfg.layers_in_memory``, older layers' meshes wait on disk: dm2.io.spill)
    fused_log : None, or a deque that receives ``(sensor_id, stamp_s)`` of every fused profile
        (a live run's latency accounting sets it)
    tsdf : the SparseTSDF being fused
    """

    def __init__(self, calibration: Calibration, monitor_cfg: MonitorConfig,
                 process: ProcessConfig, toolpath: Toolpath | None = None,
                 on_layer_done: Callable[[LayerSurface], None] | None = None,
                 bounds_O: tuple | None = None, batch_profiles: int = DEFAULT_BATCH_PROFILES,
                 max_delay_s: float = DEFAULT_MAX_DELAY_S, defer_meshing: bool = False):
        if not calibration.T_B_S:
            raise ValueError("TsdfFusion: the calibration holds no sensor pose (T_B_S is empty)")
        self.calibration = calibration
        self.cfg = monitor_cfg
        self.process = process
        voxel = monitor_cfg.voxel_mm
        self.tsdf = SparseTSDF(voxel, monitor_cfg.truncation_voxels * voxel,
                               monitor_cfg.weight_cap)
        self.sync = StreamSync(calibration.T_B_S.keys(), monitor_cfg.max_pose_gap_s,
                               monitor_cfg.reorder_window_s)
        self.layers = LayerTracker(toolpath)
        self.extractor = SurfaceExtractor(self.tsdf, monitor_cfg.min_weight)
        self.active_radius_mm = (monitor_cfg.active_radius_mm
                                 if monitor_cfg.active_radius_mm is not None
                                 else default_active_radius_mm(process))
        self.on_layer_done = on_layer_done
        self.batch_profiles = max(1, int(batch_profiles))
        self.layer_done: list[LayerSurface] = []
        keep = getattr(monitor_cfg, "layers_in_memory", None)
        self._spill = SpillStore(keep) if keep is not None else None
        self.bounds_O = None if bounds_O is None else (np.asarray(bounds_O[0], float),
                                                       np.asarray(bounds_O[1], float))
        self.points_fused = 0
        self.profiles_fused = 0
        self._point_drops: Counter = Counter()
        self._spot_B = spot_B(calibration, process.standoff_mm)
        self._axis_B = calibration.T_B_N[:3, 2].copy()
        self._last_stamp_s = float("nan")
        # a list (set by the session): (xy_O (n, 2) [mm], stamp) of each profile fused since
        self.observed_points: list[tuple] | None = None
        self._finished = False
        self.max_delay_s = float(max_delay_s)
        self.defer_meshing = bool(defer_meshing)
        self.fused_log = None
        self._sensor_ids = list(calibration.T_B_S)
        # the batch waiting to be fused, one entry per synchronised profile
        self._p_xz: list[np.ndarray] = []
        self._p_T: list[np.ndarray] = []
        self._p_sensor: list[int] = []
        self._p_stamp: list[float] = []
        self._pending_since = 0.0
        self._sensor_row = {sid: i for i, sid in enumerate(calibration.T_B_S)}
        self._T_B_S = np.stack([np.asarray(T, np.float64) for T in calibration.T_B_S.values()])
        self._T_F_O = np.ascontiguousarray(calibration.T_F_O, np.float64)
        self._merge_mm = float(monitor_cfg.ray_merge_voxels) * voxel
        pf = monitor_cfg.point_filter
        self.point_filter = (PointFilter(pf.reject_mm, pf.agree_mm, pf.max_step_mm,
                                         pf.max_run_points,
                                         self._sensor_ids) if pf.enabled else None)

    # --------------------------------------------------------------------------------- input
    @property
    def dropped(self) -> dict[str, int]:
        """What was dropped, by reason (see :mod:`dm2.fusion.sync`; ``out_of_range`` counts
        points)."""
        out = Counter(self.sync.dropped)
        out.update(self._point_drops)
        if self.point_filter is not None:
            out.update(self.point_filter.counts())
        return {k: int(v) for k, v in sorted(out.items()) if v}

    @property
    def current_layer(self) -> int:
        return self.layers.layer

    @property
    def last_fused_stamp_s(self) -> float:
        """Stamp [s] of the newest profile fused so far (NaN before the first)."""
        return self._last_stamp_s

    def feed(self, msg) -> None:
        """Take one message of any kind; bad ones are counted in :attr:`dropped`, never raised."""
        if self._finished:
            raise RuntimeError("TsdfFusion.feed: the fusion was finished")
        ready = self.sync.push(msg)
        if ready:
            self._handle(ready)
        elif self._p_xz and time.perf_counter() - self._pending_since > self.max_delay_s:
            self._flush()

    def feed_all(self, messages: Iterable) -> None:
        for m in messages:
            self.feed(m)

    def finish(self) -> list[LayerSurface]:
        """Flush the stream and close the current layer; returns all finished layers."""
        if not self._finished:
            ready = self.sync.flush()
            if ready:
                self._handle(ready)
            self._flush()
            self._finish_layer(self.layers.layer)
            self._finished = True
        return self.layer_done

    # ------------------------------------------------------------------------------- output
    def surface(self, layer: int | None = None) -> SurfaceMesh:
        """The surface now (``layer=None``) or as it was when ``layer`` finished."""
        if layer is None:
            self._flush()
            return self.extractor.update()
        for ls in self.layer_done:
            if ls.layer == layer:
                return ls.surface
        done = [ls.layer for ls in self.layer_done]
        raise KeyError(f"TsdfFusion.surface: layer {layer} has not finished (finished: {done})")

    # ------------------------------------------------------------------------------ internal
    def _handle(self, ready: list) -> None:
        for item in ready:
            if type(item) is SyncedProfile:
                if not self._p_xz:
                    self._pending_since = time.perf_counter()
                self._p_xz.append(item.xz_S)
                self._p_T.append(item.T_B_F)
                self._p_sensor.append(self._sensor_row[item.profile.sensor_id])
                self._p_stamp.append(item.profile.stamp_s)
            else:  # a LayerMark
                self._flush()
                finished = self.layers.on_mark(item.layer)
                if finished is not None:
                    self._finish_layer(finished)
        if len(self._p_xz) >= self.batch_profiles:
            self._flush()

    def _flush(self) -> None:
        """Fuse the profiles waiting in the batch (in stream order)."""
        if not self._p_xz:
            return
        xz = np.concatenate(self._p_xz) if len(self._p_xz) > 1 else self._p_xz[0]
        offsets = np.zeros(len(self._p_xz) + 1, dtype=np.int64)
        np.cumsum([len(a) for a in self._p_xz], out=offsets[1:])
        if self.point_filter is not None:  # what is not surface (dm2.fusion.point_filter)
            xz, offsets = self.point_filter.apply(xz, offsets, self._p_sensor)
        T_O_S, spots_O, axes_O = profile_frames(
            np.array(self._p_T), self._T_F_O, self._T_B_S, np.array(self._p_sensor),
            self._spot_B, self._axis_B)
        stamps, sensors = self._p_stamp, self._p_sensor
        self._p_xz, self._p_T, self._p_sensor, self._p_stamp = [], [], [], []
        start, k = 0, len(stamps)
        if self.layers.source == "toolpath":
            for j in range(k):
                finished = self.layers.on_spots(spots_O[j: j + 1])
                if finished:
                    self._fuse_range(xz, offsets, T_O_S, spots_O, axes_O, stamps, start, j)
                    start = j
                    for layer in finished:
                        self._finish_layer(layer)
        self._fuse_range(xz, offsets, T_O_S, spots_O, axes_O, stamps, start, k)
        if self.fused_log is not None:
            self.fused_log.extend((self._sensor_ids[r], t) for r, t in zip(sensors, stamps,
                                                                          strict=True))

    def _finish_layer(self, layer: int) -> None:
        if self.point_filter is not None:
            self.point_filter.close_layer(layer)
        pending = self.extractor.gather()
        log.info("layer %d done: %d blocks, %d chunks to mesh", layer, self.tsdf.n_blocks,
                 pending.n_to_mesh)
        ls = LayerSurface(int(layer), self._last_stamp_s,
                          pending if self.defer_meshing else pending.result())
        self.layer_done.append(ls)
        if self._spill is not None:  # older layers' meshes wait on disk (dm2.io.spill)
            self._spill.spill_old(self.layer_done, "_surface",
                                  ready=lambda s: isinstance(s, SurfaceMesh))
        if self.on_layer_done is not None:
            self.on_layer_done(ls)

    def _fuse_range(self, xz, offsets, T_O_S, spots_O, axes_O, stamps, a: int, b: int) -> None:
        """Register and fuse profiles ``a:b`` of a batch (one numba pass, eq 1 then eqs 2-5);
        with ``deposit_weight_cap``, each profile is fused after the weights around its spray
        axis are capped (dm2.fusion.tsdf.deposit: the spot has moved on since the previous
        profile, about a millimetre; per profile, so neither the batching nor the path before
        decides where); with ``ray_merge_voxels``, neighbouring points of a profile go as one
        ray (dm2.fusion.profile_merge)."""
        if b <= a:
            return
        cap = self.cfg.deposit_weight_cap
        deposit = None if cap is None else (self.active_radius_mm, self.active_radius_mm, cap)
        lo, hi = offsets[a], offsets[b]
        if self.observed_points is not None:  # where each profile saw the surface (in O)
            for j in range(a, b):  # per profile, so the batching does not matter
                points_O, _ = register_profile(xz[offsets[j]:offsets[j + 1]], T_O_S[j])
                self.observed_points.append((points_O, stamps[j]))
        xz_rays, off_rays, count = xz[lo:hi], offsets[a: b + 1] - lo, None
        if self._merge_mm > 0.0:  # neighbouring points as one ray (dm2.fusion.profile_merge)
            xz_rays, off_rays, count = merge_profile_points(
                np.ascontiguousarray(xz_rays), np.ascontiguousarray(off_rays), self._merge_mm)
        fused, n_out = self.tsdf.integrate_profiles(
            xz_rays, off_rays, T_O_S[a:b], spots_O[a:b], axes_O[a:b], self.active_radius_mm,
            self.bounds_O, deposit, count)
        if n_out:
            self._point_drops["out_of_range"] += n_out
        self.points_fused += fused
        self.profiles_fused += b - a
        self._last_stamp_s = stamps[b - 1]
