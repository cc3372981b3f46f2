"""The fusion pipeline: messages in, per-layer surfaces out (paper sections 4-5).

``Monitor.feed(msg)`` takes :class:`~dm2.messages.Profile`, :class:`~dm2.messages.RobotState`
and :class:`~dm2.messages.LayerMark` messages from any source (twin, recording, live drivers),
in any order within the reorder window. Profiles are synchronised with interpolated poses
(:mod:`dm2.sync`), registered into ``O`` (:mod:`dm2.registration`, eq 1), fused into the sparse
TSDF with adaptive weights around the nozzle's impact point (:mod:`dm2.tsdf`, eqs 2-5) and, at
each layer's end (:mod:`dm2.layers`), triangulated (:mod:`dm2.surface`).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from dm2.config import MonitorConfig, ProcessConfig
from dm2.frames import invert
from dm2.layers import LayerTracker
from dm2.messages import Calibration, LayerMark, Toolpath
from dm2.registration import spot_B
from dm2.surface import SurfaceExtractor, SurfaceMesh
from dm2.sync import StreamSync, SyncedProfile
from dm2.tsdf import SparseTSDF

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LayerSurface:
    """The reconstructed surface when a layer finished.

    Attributes
    ----------
    layer : int, the layer that finished
    stamp_s : float [s], stamp of the last profile fused into it (NaN if none)
    surface : SurfaceMesh in ``O``
    """

    layer: int
    stamp_s: float
    surface: SurfaceMesh


def default_active_radius_mm(process: ProcessConfig) -> float:
    """Two plume sigmas [mm] (the footprint's sigma as the near-net reference models it)."""
    from dm2.reference import plume_sigma_mm

    return 2.0 * plume_sigma_mm(process)


class Monitor:
    """In-process reconstruction of the growing part from profiles and robot poses.

    Parameters
    ----------
    calibration : sensor poses ``T_B_S``, work object on the flange ``T_F_O``, nozzle ``T_B_N``
    monitor_cfg : voxel size, truncation, weights, sync limits
    process : standoff (deposition spot) and plume (active radius default)
    toolpath : optional; splits layers when the stream carries no layer marks
    on_layer_done : optional callback ``f(LayerSurface)`` called when a layer finishes
    bounds_O : optional ``(lo (3,), hi (3,))`` [mm]; points outside are dropped as out_of_range
    batch_profiles : synchronised profiles are fused in batches of this many (3 = one frame set
        of the three cascaded sensors); layer ends, ``surface()`` and ``finish()`` flush early

    Attributes
    ----------
    layer_done : list of LayerSurface, finished layers in order
    tsdf : the SparseTSDF being fused
    """

    def __init__(self, calibration: Calibration, monitor_cfg: MonitorConfig,
                 process: ProcessConfig, toolpath: Toolpath | None = None,
                 on_layer_done: Callable[[LayerSurface], None] | None = None,
                 bounds_O: tuple | None = None, batch_profiles: int = 3):
        if not calibration.T_B_S:
            raise ValueError("Monitor: the calibration holds no sensor pose (T_B_S is empty)")
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
        self.bounds_O = None if bounds_O is None else (np.asarray(bounds_O[0], float),
                                                       np.asarray(bounds_O[1], float))
        self.points_fused = 0
        self.profiles_fused = 0
        self._point_drops: Counter = Counter()
        self._spot_B = spot_B(calibration, process.standoff_mm)
        self._axis_B = calibration.T_B_N[:3, 2].copy()
        self._last_stamp_s = float("nan")
        self._finished = False
        self._pending: list[SyncedProfile] = []

    # --------------------------------------------------------------------------------- input
    @property
    def dropped(self) -> dict[str, int]:
        """What was dropped, by reason (see :mod:`dm2.sync`; ``out_of_range`` counts points)."""
        out = Counter(self.sync.dropped)
        out.update(self._point_drops)
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
            raise RuntimeError("Monitor.feed: the monitor was finished")
        self._handle(self.sync.push(msg))

    def feed_all(self, messages: Iterable) -> None:
        for m in messages:
            self.feed(m)

    def finish(self) -> list[LayerSurface]:
        """Flush the stream and close the current layer; returns all finished layers."""
        if not self._finished:
            self._handle(self.sync.flush())
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
        raise KeyError(f"Monitor.surface: layer {layer} has not finished (finished: {done})")

    # ------------------------------------------------------------------------------ internal
    def _handle(self, ready: list) -> None:
        for item in ready:
            if isinstance(item, LayerMark):
                self._flush()
                finished = self.layers.on_mark(item.layer)
                if finished is not None:
                    self._finish_layer(finished)
            else:
                self._pending.append(item)
        if len(self._pending) >= self.batch_profiles:
            self._flush()

    def _flush(self) -> None:
        batch, self._pending = self._pending, []
        self._fuse(batch)

    def _finish_layer(self, layer: int) -> None:
        ls = LayerSurface(int(layer), self._last_stamp_s, self.extractor.update())
        self.layer_done.append(ls)
        log.info("layer %d done: %d vertices, %d faces, %d blocks", layer,
                 ls.surface.n_vertices, ls.surface.n_faces, self.tsdf.n_blocks)
        if self.on_layer_done is not None:
            self.on_layer_done(ls)

    def _fuse(self, batch: list[SyncedProfile]) -> None:
        if not batch:
            return
        T_B_F = np.stack([s.T_B_F for s in batch])
        T_O_B = invert(T_B_F @ self.calibration.T_F_O)
        spots_O = np.einsum("kij,j->ki", T_O_B[:, :3, :3], self._spot_B) + T_O_B[:, :3, 3]
        axes_O = np.einsum("kij,j->ki", T_O_B[:, :3, :3], self._axis_B)
        start = 0
        if self.layers.source == "toolpath":
            for j in range(len(batch)):
                finished = self.layers.on_spots(spots_O[j: j + 1])
                if finished:
                    self._fuse_range(batch, T_O_B, spots_O, axes_O, start, j)
                    start = j
                    for layer in finished:
                        self._finish_layer(layer)
        self._fuse_range(batch, T_O_B, spots_O, axes_O, start, len(batch))

    def _fuse_range(self, batch, T_O_B, spots_O, axes_O, a: int, b: int) -> None:
        if b <= a:
            return
        sel = batch[a:b]
        counts = np.array([len(s.xz_S) for s in sel])
        xz = np.concatenate([s.xz_S for s in sel])
        T_B_S = np.stack([self.calibration.T_B_S[s.profile.sensor_id] for s in sel])
        T_O_S = T_O_B[a:b] @ T_B_S
        R = np.repeat(T_O_S[:, :3, :3], counts, axis=0)
        origins = np.repeat(T_O_S[:, :3, 3], counts, axis=0)
        points = origins + R[:, :, 0] * xz[:, :1] + R[:, :, 2] * xz[:, 1:]
        spot = np.repeat(spots_O[a:b], counts, axis=0)
        axis = np.repeat(axes_O[a:b], counts, axis=0)
        keep = xz[:, 1] > 0.0  # in front of the sensor
        if self.bounds_O is not None:
            keep &= np.all((points >= self.bounds_O[0]) & (points <= self.bounds_O[1]), axis=1)
        n_out = int(keep.size - np.count_nonzero(keep))
        if n_out:
            self._point_drops["out_of_range"] += n_out
            points, origins, spot, axis = points[keep], origins[keep], spot[keep], axis[keep]
        rel = points - spot
        along = np.einsum("ij,ij->i", rel, axis)
        lateral2 = np.einsum("ij,ij->i", rel, rel) - along * along
        active = lateral2 <= self.active_radius_mm ** 2
        self.tsdf.integrate(origins, points, active)
        self.points_fused += len(points)
        self.profiles_fused += len(sel)
        self._last_stamp_s = sel[-1].profile.stamp_s
