"""Benchmark: HeightField.raycast throughput for 640-ray profiler fans.

A 120 x 120 mm plate at 0.25 mm cells carries a 16 mm tall rounded block; a virtual profiler
95 mm from the spot at 55 degrees elevation casts 640-ray fans at the part from several
azimuths. Prints the median rays per second over several repeats (serial and parallel kernels).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

# run as a script, this folder would come first on sys.path and benchmarks/twin.py would shadow
# the twin package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]

from twin.world import heightfield_kernels as K  # noqa: E402
from twin.world.heightfield import HeightField  # noqa: E402


def build_field() -> HeightField:
    hf = HeightField((120.0, 120.0), 0.25, 6.0)
    x, y = hf.centres_mm()
    gx, gy = np.meshgrid(x, y)
    r = np.maximum(np.abs(gx - 60.0), np.abs(gy - 60.0))
    rng = np.random.default_rng(0)
    hf.heights_mm = 16.0 / (1.0 + np.exp((r - 20.0) / 1.5)) + 0.02 * rng.standard_normal(gx.shape)
    return hf


def fans(n_fans: int = 64, n_rays: int = 640) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    origins, dirs = [], []
    elev = np.radians(55.0)
    for _ in range(n_fans):
        az = rng.uniform(0, 2 * np.pi)
        spot = np.array([60.0 + rng.uniform(-20, 20), 60.0 + rng.uniform(-20, 20), 16.0])
        view = -np.array([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])
        o = spot - 95.0 * view
        side = np.cross(view, [0.0, 0.0, 1.0])
        side /= np.linalg.norm(side)
        half = np.arctan(25.0 / 95.0)
        ang = np.linspace(-half, half, n_rays)
        d = np.cos(ang)[:, None] * view + np.sin(ang)[:, None] * side
        origins.append(np.repeat(o[None], n_rays, 0))
        dirs.append(d / np.linalg.norm(d, axis=1, keepdims=True))
    return np.stack(origins), np.stack(dirs)


def main() -> None:
    hf = build_field()
    O, D = fans()
    out = np.empty(O.shape[1])
    args = (hf._h, hf._bmax, hf.cell_mm, hf.thickness_mm, hf._zmax[0])
    for name, kernel in (("serial", K.raycast_serial), ("parallel", K.raycast_parallel)):
        kernel(*args, O[0], D[0], np.inf, out)  # compile / warm up
        rates = []
        for _ in range(7):
            t0 = time.perf_counter()
            for f in range(O.shape[0]):
                kernel(*args, O[f], D[f], np.inf, out)
            rates.append(O.shape[0] * O.shape[1] / (time.perf_counter() - t0))
        print(f"raycast {name:8s}: {np.median(rates) / 1e6:6.2f} M rays/s "
              f"(640-ray fans, median of 7)")
    t = hf.raycast(O[0], D[0])
    print(f"hit fraction of one fan: {np.isfinite(t).mean():.3f}")
    rates = []
    for _ in range(7):
        t0 = time.perf_counter()
        for f in range(O.shape[0]):
            hf.raycast(O[f], D[f])
        rates.append(O.shape[0] * O.shape[1] / (time.perf_counter() - t0))
    print(f"HeightField.raycast (API, 640-ray fans): {np.median(rates) / 1e6:6.2f} M rays/s")


if __name__ == "__main__":
    main()
