"""What a cold-spray cell adds to a profiler's output beyond its range noise (``[noise]``).

Each artefact is off at its package default (``twin.schema.NoiseConfig``), so a scenario that
does not ask for one gives the same bits as before. Those on the profile itself are applied
to the measured profile (after :mod:`twin.profiler.noise_kernels`), in this order, each from
its own stream of the profile's ``(seed, sensor, counter)``:

- **Powder in the plume.** Particles crossing the laser sheet near the jet scatter the laser
  back: a ray passing the jet's axis at distance ``d`` returns a point on the particle, in
  front of the surface, with probability ``plume_particle_prob * exp(-d^2 / 2 sigma^2)``
  times the feed against ``plume_feed_ref_g_min`` (zero while the spray is off).
- **Secondary reflections.** Light reflected once more off a neighbouring face (a wall foot,
  a concave corner, freshly sprayed metal) can outshine the direct spot: a stretch of the
  line reads a ghost behind the surface, its offset growing along the stretch. Placed at
  the profile's sharpest concave kink where it has one, else anywhere.
- **Specular dropouts and saturation.** Where a face mirrors the laser into the camera, a run
  of points is lost (half the runs) or saturated: clipped to full intensity, the clipped
  peak's centroid biased along the ray.
- **Outlier bursts.** A whole stretch misread at once: one offset in front of or behind the
  surface for all its points.
- **Slow mount drift.** The profiler's mount warms up and creeps along ``z_S``, each sensor at
  its own share of ``mount_drift_mm_min`` (:data:`DRIFT_SHARE`), growing with process time.

Clock jitter and lost profiles act on the trigger schedule (:func:`schedule_artefacts`): a
profile is exposed when it is triggered but stamped up to ``clock_jitter_ms`` off, and a
share of profiles never arrives.
"""

from __future__ import annotations

import numpy as np

from twin.schema import NoiseConfig

TAG_PROFILE = 0x60D1  # the artefacts' stream beside the noise kernels' own
TAG_SCHEDULE = 0x60D2
DRIFT_SHARE = (1.0, -0.6, 0.8)  # each sensor's share of the mount drift: mounts differ
PARTICLE_CLEAR_MM = 0.3  # a particle lies at least this far in front of the surface
KINK_MM = 0.3  # a concave kink: the range this much beyond its neighbours' mean (3 away)


def schedule_artefacts(noise: NoiseConfig, seed: int, stamps_s: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """``(reported stamps (m,) [s], kept (m,) bool)`` of the trigger schedule ``stamps_s``: each
    stamp off by up to ``clock_jitter_ms`` (uniform), each profile lost with
    ``lost_profile_prob``."""
    stamps_s = np.asarray(stamps_s, dtype=np.float64)
    if not noise.clock_jitter_ms and not noise.lost_profile_prob:
        return stamps_s, np.ones(stamps_s.shape, dtype=bool)
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFFFFFFFFFF, TAG_SCHEDULE])
    jitter_s = rng.uniform(-1.0, 1.0, stamps_s.shape) * (noise.clock_jitter_ms / 1000.0)
    kept = rng.random(stamps_s.shape) >= noise.lost_profile_prob
    return stamps_s + jitter_s, kept


class ProfileArtefacts:
    """The artefacts of one profiler, applied to its measured profiles in place.

    Parameters
    ----------
    noise : the scenario's ``[noise]``
    seed, sensor_index : the profile streams' key (with each profile's counter)
    dirs_S : (n, 3) unit ray directions in S
    z_range_mm : the measuring range ``(z_start, z_end)`` along z_S [mm]
    T_S_N : (4, 4) the nozzle in S (its origin the exit, +z the spray direction), or None:
        no plume particles
    """

    def __init__(self, noise: NoiseConfig, seed: int, sensor_index: int, dirs_S: np.ndarray,
                 z_range_mm: tuple[float, float], T_S_N: np.ndarray | None = None):
        self.noise = noise
        self.seed = int(seed) & 0xFFFFFFFFFFFFFFFF
        self.sensor_index = int(sensor_index)
        self.dirs_S = np.asarray(dirs_S, dtype=np.float64)
        self.z_range_mm = (float(z_range_mm[0]), float(z_range_mm[1]))
        self._jet = None
        if T_S_N is not None and noise.plume_particle_prob > 0:
            self._jet = self._jet_crossing(np.asarray(T_S_N, dtype=np.float64))

    def _jet_crossing(self, T_S_N: np.ndarray):
        """``(t (n,), d (n,))``: where along each ray [mm] it passes closest to the jet's axis
        downstream of the exit, and how close [mm] (inf where it never does)."""
        o, a = T_S_N[:3, 3], T_S_N[:3, 2]
        d = self.dirs_S
        w0 = -o
        b = d @ a
        dd, e = d @ w0, a @ w0
        denom = np.maximum(1.0 - b * b, 1e-12)
        t = (b * e - dd) / denom
        s = (e - b * dd) / denom
        gap = w0 + t[:, None] * d - s[:, None] * a
        dist = np.linalg.norm(gap, axis=1)
        dist[(s <= 0.0) | (t <= 0.0)] = np.inf
        return t, dist

    def apply(self, xz: np.ndarray, valid: np.ndarray, intensity: np.ndarray, stamp_s: float,
              counter: int, spray: float = 1.0) -> None:
        """The artefacts on one measured profile (``xz (n, 2)`` [mm, S], NaN where invalid,
        ``valid (n,)``, ``intensity (n,) float32``), in place; ``spray``: the feed now over
        ``plume_feed_ref_g_min`` (0 while the spray is off)."""
        nz = self.noise
        rng = np.random.default_rng([self.seed, TAG_PROFILE, self.sensor_index, int(counter)])
        u = rng.random(8)  # the per-profile decisions, drawn whether used or not
        r = np.where(valid, np.hypot(xz[:, 0], xz[:, 1]), np.nan)
        r_in = r.copy()
        if self._jet is not None and spray > 0:
            self._particles(rng, r, valid, intensity, spray)
        if u[0] < nz.ghost_line_prob:
            a, b = self._stretch(rng, nz.ghost_line_points, self._kink(r))
            lo, hi = nz.ghost_line_offset_mm
            off = (lo + (hi - lo) * u[1]) * (1.0 + np.arange(b - a) / max(b - a, 1))
            r[a:b] += off
            intensity[a:b] *= np.float32(0.5)
        if u[2] < nz.specular_run_prob:
            a, b = self._stretch(rng, nz.specular_run_points, None)
            if u[3] < 0.5:
                valid[a:b] = False
            else:
                r[a:b] += nz.saturation_bias_mm
                intensity[a:b] = np.where(valid[a:b], np.float32(1.0), intensity[a:b])
        if u[4] < nz.burst_prob:
            a, b = self._stretch(rng, nz.burst_points, None)
            lo, hi = nz.burst_offset_mm
            r[a:b] += (lo + (hi - lo) * u[5]) * (1.0 if u[6] < 0.5 else -1.0)
        # only the points an artefact moved are recomputed from their range (the others
        # keep their bits)
        moved = np.isfinite(r) & ~(r == r_in)
        x = np.where(moved, r * self.dirs_S[:, 0], xz[:, 0])
        z = np.where(moved, r * self.dirs_S[:, 2], xz[:, 1])
        if nz.mount_drift_mm_min:
            z = z + nz.mount_drift_mm_min * DRIFT_SHARE[self.sensor_index] * stamp_s / 60.0
        z0, z1 = self.z_range_mm
        valid &= np.isfinite(z) & (z >= z0) & (z <= z1)
        xz[:, 0] = np.where(valid, x, np.nan)
        xz[:, 1] = np.where(valid, z, np.nan)
        intensity[~valid] = np.float32(0.0)

    def _particles(self, rng, r, valid, intensity, spray):
        nz = self.noise
        t, dist = self._jet
        p = nz.plume_particle_prob * spray * np.exp(
            -0.5 * (dist / nz.plume_particle_sigma_mm) ** 2)
        at = t + rng.normal(0.0, 0.5 * nz.plume_particle_sigma_mm, t.shape)
        hit = (rng.random(t.shape) < p) & (at > 0.0)
        hit &= ~valid | (at < r - PARTICLE_CLEAR_MM)
        r[hit] = at[hit]
        valid[hit] = True
        intensity[hit] = rng.uniform(0.1, 1.0, int(hit.sum())).astype(np.float32)

    def _kink(self, r):
        """The ray at the profile's sharpest concave kink (the range beyond its neighbours'
        mean by more than ``KINK_MM``), or None."""
        if r.size < 7:
            return None
        kink = r[3:-3] - 0.5 * (r[:-6] + r[6:])
        kink = np.where(np.isfinite(kink), kink, -np.inf)
        k = int(np.argmax(kink))
        return k + 3 if kink[k] > KINK_MM else None

    def _stretch(self, rng, points, at):
        """``(a, b)``: a stretch of ``points`` [min, max] rays, starting at ``at`` or on
        either side of it (None: anywhere)."""
        n = self.dirs_S.shape[0]
        length = int(rng.integers(points[0], points[1] + 1))
        length = min(length, n)
        if at is None:
            a = int(rng.integers(0, n - length + 1))
        else:
            a = at if rng.random() < 0.5 else at - length + 1
            a = min(max(a, 0), n - length)
        return a, a + length
