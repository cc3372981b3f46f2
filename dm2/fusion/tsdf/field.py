"""Sparse truncated signed distance field with adaptive weights (paper section 5.1, eqs 2-5).

Storage
-------
Voxels of edge ``voxel_mm`` are grouped in blocks of 8**3 voxels that are allocated only where a
ray has passed (like VDB leaf nodes). Block rows live in growable preallocated arrays
(``voxels`` of shape ``(capacity, 512, 2)`` float32: signed distance and weight side by side)
found through an open-addressing hash of the block coordinates; memory is ``~4 KiB`` per
observed block plus the hash table.

Update
------
Every measured point ``p`` with its sensor origin ``o`` (both in ``O``) updates the voxels its ray
crosses within ``truncation_mm`` of ``p`` with the projective signed distance ``d`` (positive in
front of the surface, towards the sensor) by the weighted running average of eqs 2-3::

    D_t = (W_{t-1} D_{t-1} + w_t d_t) / (W_{t-1} + w_t),    W_t = W_{t-1} + w_t

Weight functions (eqs 4-5). The paper writes ``w(d)`` with ``d`` measured *behind* the point
(``d < 0`` in front). We keep that reading: ``w_I`` is 1 in front of the point and falls
linearly to 0 at ``truncation_mm`` behind it (measurements are less certain inside the part).
The paper leaves ``w_A`` on ``0 < d < delta`` open; we let it fall off behind the point as
``w_I`` does, so the two differ only by the active region's weight cap. Behind a point lies
material only where the surface is flat at the truncation's scale: a ray grazing a rim ends on
it, and its band behind runs on into the free space beyond. Where the spray had just reset the
weights (:mod:`dm2.fusion.tsdf.deposit`), one such ray at full weight put a surface 0.4-0.5 mm
above the twin's true one for a moment, and real-time overbuild alarms followed (on the plate
with a hole's inner wall; 15 mm from the default run's corner dwell).

Weight cap (our addition)
-------------------------
The paper's running average gives every past measurement equal say, so a surface that keeps
growing is averaged with its own history and lags behind. Before a voxel in the *active* region
(within ``active_radius_mm`` of the nozzle axis) is updated, its stored weight is clipped to
``weight_cap``; each new measurement then moves ``D`` by at least ``1 / (weight_cap + 1)`` of the
way, so a 1 mm rise is followed within a few sensor passes. Voxels in the *inactive* region
accumulate weight up to ``inactive_weight_cap`` (default :data:`INACTIVE_WEIGHT_CAP`), which
averages sensor noise down and keeps the finished surface still. ``weight_cap`` therefore trades
noise (higher) against lag (lower).

The inactive cap is a window too: surfaces outside the active region still change (overspray
settles on the plate and the wall foot around the part, the plume's flank reaches beyond the
active radius). With weights let to grow to 1e4, such a surface was the mean of its whole
history: on the twisted tower the plate ring at the wall foot lagged 0.9 mm behind the truth
after 23 layers (true height 2.56 mm, reconstructed 1.75 mm, weights ~300) and made 51 % of
the layer's squared error; with the cap at 50 observations the layer's RMS fell from 0.186 to
0.136 mm and its p95 from 0.361 to 0.248 mm, the same as the first layer's.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from dm2.fusion.tsdf import kernels as K
from dm2.fusion.tsdf.bundles import FusionParams, profile_batch, ray_batch
from dm2.fusion.tsdf.column_carve import carve_columns
from dm2.fusion.tsdf.dense import gather_dense
from dm2.fusion.tsdf.deposit import cap_columns, cap_near_axis, fuse_profiles_capped
from dm2.fusion.tsdf.threads import NO_DEPOSIT, SplitBuffers, fuse_split

log = logging.getLogger(__name__)

# Weight of inactive voxels saturates here: about the last 50 observations make the surface
# (see "Weight cap" above); sensor noise is averaged down by sqrt(50) and a changing surface is
# followed within that many observations.
INACTIVE_WEIGHT_CAP = 50.0
_NO_BOUNDS = np.zeros(3)
# Batches with fewer points are fused by the serial kernel (thread hand-off would dominate).
MIN_SPLIT_POINTS = 4096


class SparseTSDF:
    """Sparse block TSDF in the work-object frame ``O``.

    Parameters
    ----------
    voxel_mm : float [mm], voxel edge (0 < voxel_mm <= 2)
    truncation_mm : float [mm], half width of the band updated around each measured point
    weight_cap : float, stored weight is clipped to this before an active-region update
    inactive_weight_cap : float, stored weights never exceed this (the inactive region's
        window; default ``max(INACTIVE_WEIGHT_CAP, weight_cap)``, at least ``weight_cap``)
    initial_blocks : int, preallocated block rows (grows by doubling)
    threads : int, 1 or 2 (default: 2 where the machine has 2 or more cores). With 2, batches
        of at least ``MIN_SPLIT_POINTS`` points are fused by two threads that own alternate
        block columns; every voxel is bit-identical to the one-thread result (block slots are
        allocated in another, still deterministic, order).
    """

    def __init__(self, voxel_mm: float = 0.5, truncation_mm: float = 1.5,
                 weight_cap: float = 8.0, initial_blocks: int = 1024,
                 threads: int | None = None,
                 inactive_weight_cap: float | None = None):
        if not 0 < voxel_mm <= 2.0:
            raise ValueError(f"SparseTSDF.voxel_mm: {voxel_mm} outside (0, 2] mm")
        if truncation_mm <= 0:
            raise ValueError(f"SparseTSDF.truncation_mm: must be > 0, got {truncation_mm}")
        if weight_cap <= 0:
            raise ValueError(f"SparseTSDF.weight_cap: must be > 0, got {weight_cap}")
        if inactive_weight_cap is None:
            inactive_weight_cap = max(INACTIVE_WEIGHT_CAP, weight_cap)
        if not inactive_weight_cap >= weight_cap:
            raise ValueError(f"SparseTSDF.inactive_weight_cap: {inactive_weight_cap} must be "
                             f">= weight_cap {weight_cap}")
        self.voxel_mm = float(voxel_mm)
        self.truncation_mm = float(truncation_mm)
        self.weight_cap = float(weight_cap)
        self.inactive_weight_cap = float(inactive_weight_cap)
        if threads is None:
            threads = 2 if (os.cpu_count() or 1) >= 2 else 1
        if threads not in (1, 2):
            raise ValueError(f"SparseTSDF.threads: 1 or 2, got {threads}")
        self.threads = int(threads)
        # CPU seconds of the two-thread path so far: serial commits of staged blocks, thread 0,
        # thread 1, and the threaded phases' critical path (the slower thread of each run)
        self.split_cpu_s = np.zeros(4)
        self._split_buffers = SplitBuffers()
        cap = max(64, int(initial_blocks))
        self.voxels = np.zeros((cap, K.BLOCK_VOXELS, 2), dtype=np.float32)
        self.block_keys = np.full(cap, K.EMPTY, dtype=np.int64)
        self.touched = np.zeros(cap, dtype=np.bool_)
        self._state = np.zeros(1, dtype=np.int64)  # number of allocated blocks
        self._table_keys, self._table_slots = K.rebuild_hash(self.block_keys, 0,
                                                             _pow2_at_least(4 * cap))

    # ----------------------------------------------------------------------------- properties
    @property
    def n_blocks(self) -> int:
        return int(self._state[0])

    @property
    def tsdf_mm(self) -> np.ndarray:
        """Signed distances ``(capacity, 512)`` float32 [mm] of the block rows (a view)."""
        return self.voxels[:, :, 0]

    @property
    def weight(self) -> np.ndarray:
        """Weights ``(capacity, 512)`` float32 of the block rows (a view)."""
        return self.voxels[:, :, 1]

    @property
    def block_mm(self) -> float:
        return self.voxel_mm * K.BLOCK

    def nbytes(self) -> int:
        """Bytes held by the field's arrays."""
        return int(self.voxels.nbytes + self.block_keys.nbytes
                   + self.touched.nbytes + self._table_keys.nbytes + self._table_slots.nbytes)

    def block_coords(self) -> np.ndarray:
        """Integer coordinates ``(n_blocks, 3)`` of the allocated blocks."""
        return K.unpack_keys(self.block_keys[: self.n_blocks])

    # ------------------------------------------------------------------------------- update
    def integrate(self, origins_O: np.ndarray, points_O: np.ndarray,
                  active: np.ndarray | None = None) -> None:
        """Fuse rays from ``origins_O (n, 3)`` [mm] to measured ``points_O (n, 3)`` [mm].

        ``active (n,) bool`` marks rays whose point lies in the active deposition region.
        Points must be finite (the pipeline drops NaN points before this). Consecutive rays from
        the same origin are taken as a profile's points in order: one whose neighbour reaches
        more than 1 mm farther is an occluding edge and writes no band behind its point
        (dm2.fusion.tsdf.point_rays), as in :meth:`integrate_profiles`.
        """
        o = np.ascontiguousarray(origins_O, dtype=np.float64)
        p = np.ascontiguousarray(points_O, dtype=np.float64)
        if o.shape != p.shape or p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"SparseTSDF.integrate: origins {o.shape} and points {p.shape} "
                             "must both be (n, 3)")
        a = np.zeros(p.shape[0], dtype=np.bool_) if active is None else \
            np.ascontiguousarray(active, dtype=np.bool_)
        if a.shape != (p.shape[0],):
            raise ValueError(f"SparseTSDF.integrate: active {a.shape} != ({p.shape[0]},)")
        if self.threads == 2 and p.shape[0] >= MIN_SPLIT_POINTS:
            fuse_split(self, False, False, ray_batch(o, p, a),
                       self._params(0.0, _NO_BOUNDS, _NO_BOUNDS), np.zeros(2, dtype=np.int64))
            return
        start = 0
        while start < p.shape[0]:  # flat arguments: a call from Python per batch of rays
            start = K.integrate_rays(o, p, a, self.voxel_mm, self.truncation_mm,
                                     self.weight_cap, self.inactive_weight_cap, self._table_keys,
                                     self._table_slots, self.block_keys, self.voxels,
                                     self.touched, self._state, start)
            if start < p.shape[0]:
                self._grow()

    def integrate_profiles(self, xz_S: np.ndarray, offsets: np.ndarray, T_O_S: np.ndarray,
                           spot_O: np.ndarray, axis_O: np.ndarray, active_radius_mm: float,
                           bounds_O: tuple | None = None,
                           deposit: tuple | None = None,
                           count: np.ndarray | None = None) -> tuple[int, int]:
        """Register profiles into ``O`` (eq 1) and fuse them, in one pass without temporaries.

        Parameters
        ----------
        xz_S : (n, 2) float64 [mm], laser-plane points of all profiles, finite, in stream order
        offsets : (k + 1,) int64, profile ``j`` owns ``xz_S[offsets[j]:offsets[j + 1]]``
        T_O_S : (k, 4, 4) float64, sensor pose of each profile in ``O`` at its stamp
        spot_O, axis_O : (k, 3) float64, deposition spot [mm] and unit spray axis at its stamp
        active_radius_mm : float [mm], points this close to the nozzle axis are active
        bounds_O : optional ``(lo (3,), hi (3,))`` [mm]; points outside are not fused
        deposit : optional ``(radius_mm, half_length_mm, weight_cap)``: before each profile is
            fused, the weights around its spray axis are capped (:mod:`.deposit`; with two
            threads each caps its own block columns)
        count : optional (n,) int64, how many measured points each ``xz_S`` point stands for
            (:mod:`dm2.fusion.profile_merge`; its weight's multiple); 1 each by default

        Returns
        -------
        (fused, out_of_range) : numbers of measured points fused and of those skipped (behind
        the sensor, ``z <= 0``, or outside ``bounds_O``), each point counted ``count`` times
        """
        xz = np.ascontiguousarray(xz_S, dtype=np.float64)
        off = np.ascontiguousarray(offsets, dtype=np.int64)
        k = off.shape[0] - 1
        T = np.ascontiguousarray(T_O_S, dtype=np.float64)
        spot = np.ascontiguousarray(spot_O, dtype=np.float64)
        axis = np.ascontiguousarray(axis_O, dtype=np.float64)
        mult = (np.ones(xz.shape[0], dtype=np.int64) if count is None else
                np.ascontiguousarray(count, dtype=np.int64))
        if xz.ndim != 2 or xz.shape[1] != 2 or k < 0 or T.shape != (k, 4, 4) or \
                spot.shape != (k, 3) or axis.shape != (k, 3) or mult.shape != xz.shape[:1] or \
                (k and (off[0] != 0 or off[-1] != xz.shape[0] or np.any(np.diff(off) < 0))):
            raise ValueError(f"SparseTSDF.integrate_profiles: xz_S {xz.shape}, offsets "
                             f"{off.shape}, T_O_S {T.shape}, spot_O {spot.shape}, axis_O "
                             f"{axis.shape}, count {mult.shape} do not describe one batch of "
                             f"profiles")
        use_bounds = bounds_O is not None
        lo, hi = (np.asarray(bounds_O[0], np.float64), np.asarray(bounds_O[1], np.float64)) \
            if use_bounds else (_NO_BOUNDS, _NO_BOUNDS)
        counts = np.zeros(2, dtype=np.int64)
        r2 = float(active_radius_mm) ** 2
        start, n = 0, xz.shape[0]
        # with the deposit cap each profile is capped, then fused, profile by profile
        kernel, cap = (K.fuse_profiles, ()) if deposit is None else \
            (fuse_profiles_capped, tuple(float(x) for x in deposit))
        if self.threads == 2 and n >= MIN_SPLIT_POINTS:
            fuse_split(self, True, use_bounds, profile_batch(xz, off, T, spot, axis, mult),
                       self._params(r2, lo, hi), counts, cap or NO_DEPOSIT)
            start = n
        while start < n:  # flat arguments: a call from Python per profile (see bundles)
            start = kernel(xz, off, T, spot, axis, mult, self.voxel_mm, self.truncation_mm,
                           self.weight_cap, self.inactive_weight_cap, r2, lo, hi, use_bounds,
                           start, self._table_keys, self._table_slots, self.block_keys,
                           self.voxels, self.touched, self._state, counts, *cap)
            if start < n:
                self._grow()
        return int(counts[1]), int(counts[0])

    def _params(self, active_r2_mm2: float, bounds_lo, bounds_hi) -> FusionParams:
        """The kernels' constants of one call (``bounds_lo, bounds_hi (3,)`` [mm, O])."""
        return FusionParams(self.voxel_mm, self.truncation_mm, self.weight_cap,
                            self.inactive_weight_cap, active_r2_mm2, bounds_lo, bounds_hi)

    def cap_weights_near_axis(self, spot_O, axis_O, radius_mm: float, half_length_mm: float,
                              weight_cap: float) -> int:
        """Cap the weights around a spray axis (dm2.fusion.tsdf.deposit); returns how many
        voxels were capped. Signed distances are kept."""
        return int(cap_near_axis(self._table_keys, self._table_slots, self.voxels, self.voxel_mm,
                                 np.asarray(spot_O, np.float64), np.asarray(axis_O, np.float64),
                                 float(radius_mm), float(half_length_mm), float(weight_cap)))

    def cap_weights_in_columns(self, xy_O, z_lo_mm, z_hi_mm, weight_cap: float) -> int:
        """Cap the weights of the voxel columns holding ``xy_O (k, 2)`` [mm] between
        ``z_lo_mm (k,)`` and ``z_hi_mm (k,)`` (dm2.fusion.tsdf.deposit.cap_columns); returns how
        many voxels were capped. Signed distances are kept."""
        xy = np.asarray(xy_O, np.float64).reshape(-1, 2)
        return int(cap_columns(self._table_keys, self._table_slots, self.voxels, self.voxel_mm,
                               np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1]),
                               np.asarray(z_lo_mm, np.float64), np.asarray(z_hi_mm, np.float64),
                               float(weight_cap)))

    def carve_buried_in_columns(self, xy_O, z_lo_mm, z_hi_mm, stale_below: float) -> int:
        """Carve the stale free slabs enclosed by material in the voxel columns holding
        ``xy_O (k, 2)`` [mm], walked from ``z_hi_mm (k,)`` down to ``z_lo_mm (k,)``, whose free
        voxels weigh less than ``stale_below`` (dm2.fusion.tsdf.column_carve); returns how many
        voxels were carved."""
        xy = np.asarray(xy_O, np.float64).reshape(-1, 2)
        return int(carve_columns(self._table_keys, self._table_slots, self.voxels, self.touched,
                                 self.voxel_mm, np.ascontiguousarray(xy[:, 0]),
                                 np.ascontiguousarray(xy[:, 1]), np.asarray(z_lo_mm, np.float64),
                                 np.asarray(z_hi_mm, np.float64), float(self.truncation_mm),
                                 float(stale_below)))

    def _grow(self, extra: int = 0) -> None:
        """Room for ``extra`` more blocks plus one ray's worth: the block arrays and the hash
        table (kept at most half full) double until they fit."""
        need = self.n_blocks + int(extra) + K.MAX_NEW_BLOCKS_PER_RAY
        cap = self.voxels.shape[0]
        if need > cap:
            new_cap = cap
            while need > new_cap:
                new_cap *= 2
            log.debug("SparseTSDF: growing block storage %d -> %d blocks", cap, new_cap)
            self.voxels = _resized(self.voxels, new_cap, 0.0)
            self.block_keys = _resized(self.block_keys, new_cap, K.EMPTY)
            self.touched = _resized(self.touched, new_cap, False)
        table = self._table_keys.shape[0]
        if need <= table // 2 and extra:
            return  # the table has room: no rebuild
        while need > table // 2:
            table *= 2
        self._table_keys, self._table_slots = K.rebuild_hash(self.block_keys, self.n_blocks,
                                                             table)

    # ------------------------------------------------------------------------------ queries
    def take_touched(self) -> np.ndarray:
        """Coordinates ``(k, 3)`` of blocks updated since the last call; clears the marks."""
        idx = np.flatnonzero(self.touched[: self.n_blocks])
        self.touched[idx] = False
        return K.unpack_keys(self.block_keys[idx])

    def dense(self, origin_voxel: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
        """Dense sub-volume from voxel index ``origin_voxel (3,)``: ``(tsdf_mm, weight)`` of
        ``shape (nx, ny, nz)`` float32; unobserved voxels hold ``+truncation_mm`` and weight 0."""
        return gather_dense(self._table_keys, self._table_slots, self.voxels,
                            np.asarray(origin_voxel, dtype=np.int64),
                            np.asarray(shape, dtype=np.int64), np.float32(self.truncation_mm))

    def sample(self, points_O: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest-voxel ``(tsdf_mm (n,), weight (n,))`` at ``points_O (n, 3)`` [mm]."""
        p = np.asarray(points_O, dtype=np.float64).reshape(-1, 3)
        v = np.floor(p / self.voxel_mm).astype(np.int64)
        d = np.full(len(p), self.truncation_mm, dtype=np.float32)
        w = np.zeros(len(p), dtype=np.float32)
        for i, vi in enumerate(v):
            dd, ww = self.dense(vi, (1, 1, 1))
            d[i], w[i] = dd[0, 0, 0], ww[0, 0, 0]
        return d, w


def _pow2_at_least(n: int) -> int:
    return 1 << max(6, int(np.ceil(np.log2(max(n, 1)))))


def _resized(a: np.ndarray, rows: int, fill) -> np.ndarray:
    out = np.zeros((rows,) + a.shape[1:], dtype=a.dtype) if fill == 0 else \
        np.full((rows,) + a.shape[1:], fill, dtype=a.dtype)
    out[: a.shape[0]] = a
    return out
