"""Analytic synthetic scenes for the fusion tests: a plate with a box and a sphere cap, three
profilers around a fixed nozzle, the plate moved under them along a raster.

Everything here is exact geometry (ray / plane, slab and sphere intersections), so the true
surface is known to machine precision. The tests at the bottom check the scene itself.
"""

from __future__ import annotations

import numpy as np

from dm2.core.frames import from_euler_deg, invert, look_at, make_T
from dm2.core.messages import Calibration, Profile, RobotState

STANDOFF_MM = 30.0
SPOT_B = np.array([1000.0, 0.0, 500.0])


class Scene:
    """Plate top ``z = 0`` plus optional axis-aligned boxes ``(lo, hi)`` and sphere caps
    ``(centre, radius)`` (the parts above ``z = 0``), all in ``O`` [mm]."""

    def __init__(self, boxes=(), spheres=()):
        self.boxes = [(np.asarray(lo, float), np.asarray(hi, float)) for lo, hi in boxes]
        self.spheres = [(np.asarray(c, float), float(r)) for c, r in spheres]

    def raycast(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Distance ``(n,)`` along unit rays to the first hit (inf on a miss)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(d[:, 2] < 0, -o[:, 2] / d[:, 2], np.inf)
            for lo, hi in self.boxes:
                t1, t2 = (lo - o) / d, (hi - o) / d
                tn = np.nanmax(np.minimum(t1, t2), axis=1)
                tf = np.nanmin(np.maximum(t1, t2), axis=1)
                hit = (tn <= tf) & (tn > 0)
                t = np.where(hit & (tn < t), tn, t)
            for c, r in self.spheres:
                oc = o - c
                b = np.einsum("ij,ij->i", oc, d)
                disc = b * b - (np.einsum("ij,ij->i", oc, oc) - r * r)
                th = -b - np.sqrt(np.maximum(disc, 0))
                z = o[:, 2] + th * d[:, 2]
                hit = (disc > 0) & (th > 0) & (z >= 0)
                t = np.where(hit & (th < t), th, t)
        return t

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """Signed distance ``(n,)`` [mm] to the true surface (negative inside the solid)."""
        s = p[:, 2].copy()  # the plate: solid below z = 0
        for lo, hi in self.boxes:
            c, h = (lo + hi) / 2, (hi - lo) / 2
            q = np.abs(p - c) - h
            box = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
            s = np.minimum(s, box)
        for c, r in self.spheres:
            s = np.minimum(s, np.linalg.norm(p - c, axis=1) - r)
        return s


def make_calibration(T_F_O=None) -> Calibration:
    """Three sensors 95 mm from the spot at 55 deg elevation, azimuths 90/210/330 deg."""
    sensors = {}
    el = np.radians(55.0)
    for sid, az in zip(("S1", "S2", "S3"), np.radians([90.0, 210.0, 330.0]), strict=True):
        pos = SPOT_B + 95.0 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                        np.sin(el)])
        sensors[sid] = look_at(pos, SPOT_B)
    T_B_N = make_T(np.diag([1.0, -1.0, -1.0]), SPOT_B + [0, 0, STANDOFF_MM])
    if T_F_O is None:
        T_F_O = from_euler_deg([-60.0, -60.0, 150.0], [10.0, 0.0, 0.0])
    return Calibration(sensors, T_F_O, T_B_N)


def T_B_F_for_spot(cal: Calibration, spot_O) -> np.ndarray:
    """Flange pose that puts ``spot_O`` under the nozzle (plate level, no tilt)."""
    T_B_O = make_T(None, SPOT_B - np.asarray(spot_O, float))
    return T_B_O @ invert(cal.T_F_O)


def scan_profile(scene, cal, sid, T_B_F, stamp_s, counter, rng, noise_mm=0.0, n_rays=640,
                 z_range=(70.0, 120.0)) -> tuple[Profile, np.ndarray]:
    """One profile of sensor ``sid`` at flange pose ``T_B_F``; also the true hits ``(n, 3)`` in
    ``O`` (NaN where the sensor reports nothing)."""
    T_O_S = invert(T_B_F @ cal.T_F_O) @ cal.T_B_S[sid]
    ang = np.linspace(-0.26, 0.26, n_rays)
    dirs_S = np.column_stack([np.sin(ang), np.zeros(n_rays), np.cos(ang)])
    d_O = dirs_S @ T_O_S[:3, :3].T
    o_O = np.broadcast_to(T_O_S[:3, 3], d_O.shape)
    t = scene.raycast(np.ascontiguousarray(o_O), d_O)
    if noise_mm > 0:
        t = t + rng.normal(0.0, noise_mm, n_rays)
    xz = np.column_stack([t * dirs_S[:, 0], t * dirs_S[:, 2]])
    valid = np.isfinite(t) & (xz[:, 1] >= z_range[0]) & (xz[:, 1] <= z_range[1])
    xz[~valid] = np.nan
    hits = o_O + d_O * t[:, None]
    hits[~valid] = np.nan
    prof = Profile(sid, stamp_s, counter, xz, valid, np.where(valid, 0.8, 0).astype(np.float32))
    return prof, hits


def raster_run(scene, cal, lines_O, step_mm=1.0, dt_s=0.1, state_hz=250.0, noise_mm=0.0,
               seed=0, t0_s=0.0, counter0=0, cascade_s=0.02, n_rays=640):
    """Messages of a run along straight ``lines_O`` [(start (3,), end (3,)), ...] of the spot,
    one frame set per ``step_mm`` at ``dt_s`` intervals; robot states at ``state_hz``.

    Returns ``(messages in stamp order, true hits (n, 3) of all valid points)``.
    """
    rng = np.random.default_rng(seed)
    waypoints = []
    for a, b in lines_O:
        a, b = np.asarray(a, float), np.asarray(b, float)
        k = max(int(np.ceil(np.linalg.norm(b - a) / step_mm)), 1)
        waypoints.extend(a + (b - a) * i / k for i in range(k + 1))
    waypoints = np.array(waypoints)
    times = t0_s + dt_s * np.arange(len(waypoints))

    def spot_at(t):
        return np.column_stack([np.interp(t, times, waypoints[:, j]) for j in range(3)])

    t_states = np.arange(t0_s - 0.1, times[-1] + 2 * cascade_s + 0.1, 1.0 / state_hz)
    spots = spot_at(t_states)
    msgs = [RobotState(t, i, np.zeros(6), T_B_F_for_spot(cal, s))
            for i, (t, s) in enumerate(zip(t_states, spots, strict=True))]
    hits = []
    counter = counter0
    for t in times:
        for j, sid in enumerate(("S1", "S2", "S3")):
            ts = t + j * cascade_s
            prof, h = scan_profile(scene, cal, sid, T_B_F_for_spot(cal, spot_at(ts)[0]), ts,
                                   counter % (1 << 24), rng, noise_mm, n_rays)
            msgs.append(prof)
            hits.append(h[prof.valid])
        counter += 1
    msgs.sort(key=lambda m: m.stamp_s)
    return msgs, np.concatenate(hits)


def raster_lines(x_range, y_values, z=0.0):
    """Boustrophedon lines along x at each y."""
    lines = []
    for i, y in enumerate(y_values):
        a, b = [x_range[0], y, z], [x_range[1], y, z]
        lines.append((a, b) if i % 2 == 0 else (b, a))
    return lines


# ---------------------------------------------------------------------------- scene checks
def test_raycast_hits_lie_on_the_surface():
    scene = Scene(boxes=[((50, 50, 0), (70, 70, 6))], spheres=[((40, 80, -5), 10.0)])
    cal = make_calibration()
    rng = np.random.default_rng(1)
    prof, hits = scan_profile(scene, cal, "S2", T_B_F_for_spot(cal, [60, 60, 6]), 0.0, 0, rng)
    h = hits[prof.valid]
    assert len(h) > 500
    np.testing.assert_allclose(scene.sdf(h), 0.0, atol=1e-9)


def test_sensor_sees_the_spot_at_the_centre_of_its_line():
    cal = make_calibration()
    rng = np.random.default_rng(2)
    for sid in ("S1", "S2", "S3"):
        prof, hits = scan_profile(Scene(), cal, sid, T_B_F_for_spot(cal, [60, 60, 0]), 0.0, 0,
                                  rng)
        mid = hits[320]
        np.testing.assert_allclose(mid, [60, 60, 0], atol=0.1)
        np.testing.assert_allclose(prof.xz_S[320, 1], 95.0, atol=0.1)
