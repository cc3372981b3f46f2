"""Numba kernels for the virtual profiler's sensor noise: each profile's random draws, and the
noise and output format applied to a noise-free trace.

Every profile draws from its own counter-based stream: SplitMix64 (as in
:mod:`twin.world.deposition_kernels`) started from a key mixed from ``(seed, sensor, counter)``, so
a
profile's noise does not depend on the order in which profiles are generated and costs no
generator object. Uniforms take the top 53 bits of a draw; normals come from Marsaglia's
polar method, both values of each pair in turn. The draws of a profile of ``n`` points, in order:
``n`` range-noise normals, ``n + 2 * half`` white normals convolved with the speckle kernel
(``2 * half + 1`` taps) into ``n`` correlated ones, ``n`` dropout uniforms, ``n`` ghost
uniforms, ``n`` ghost offsets uniform in ``[lo, hi)`` [mm].
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from twin.world.deposition_kernels import next_u64, uniform

# Reason codes, as in twin.profiler.sensor.
VALID = 0
NO_SURFACE = 1
DROPOUT = 7


@njit(cache=True)
def stream_state(seed, sensor, counter):
    """The SplitMix64 state ``(1,) uint64`` of profile ``counter`` of ``sensor`` (an index)
    under the scenario ``seed`` (all non-negative integers below 2**64)."""
    state = np.empty(1, dtype=np.uint64)
    state[0] = np.uint64(seed)
    state[0] = next_u64(state)
    state[0] = next_u64(state) ^ np.uint64(sensor)
    state[0] = next_u64(state) ^ np.uint64(counter)
    state[0] = next_u64(state)
    return state


@njit(cache=True)
def _fill_normal(state, out):
    """Standard normals into ``out`` (Marsaglia's polar method, both values of each pair)."""
    m = out.shape[0]
    k = 0
    while k < m:
        u = 2.0 * uniform(state) - 1.0
        v = 2.0 * uniform(state) - 1.0
        s = u * u + v * v
        if s >= 1.0 or s == 0.0:
            continue
        f = math.sqrt(-2.0 * math.log(s) / s)
        out[k] = u * f
        if k + 1 < m:
            out[k + 1] = v * f
        k += 2


@njit(cache=True, nogil=True)
def noise_draws(seed, sensor, counter, kernel, lo, hi, gauss, speckle, u_drop, u_ghost,
                ghost_mm):
    """Fill the ``(n,)`` draws of one profile (see the module docstring for their order);
    ``kernel (2 * half + 1,)`` is the unit-energy speckle kernel, ``[lo, hi)`` [mm] the ghost
    offsets."""
    n = gauss.shape[0]
    m = kernel.shape[0]
    state = stream_state(seed, sensor, counter)
    _fill_normal(state, gauss)
    white = np.empty(n + m - 1)
    _fill_normal(state, white)
    for i in range(n):  # np.convolve(white, kernel, "valid"): the kernel runs reversed
        acc = 0.0
        for j in range(m):
            acc += white[i + j] * kernel[m - 1 - j]
        speckle[i] = acc
    for i in range(n):
        u_drop[i] = uniform(state)
    for i in range(n):
        u_ghost[i] = uniform(state)
    for i in range(n):
        ghost_mm[i] = lo + (hi - lo) * uniform(state)


@njit(cache=True, nogil=True)
def apply_noise(range_mm, reason, cos_inc, gauss, speckle, u_drop, u_ghost, ghost_mm,
                range_sigma, speckle_sigma, outlier_prob, dropout_prob, dir_x, dir_z,
                z_start, z_end, out_xz, out_valid, out_intensity):
    """The sensor's noise and output format, from the profile's random draws: range noise and
    speckle along each ray, ghosts beyond the surface at half intensity, dropouts, the
    measuring range; invalid points get NaN coordinates and zero intensity."""
    for k in range(range_mm.shape[0]):
        r = range_mm[k] + range_sigma * gauss[k] + speckle_sigma * speckle[k]
        why = reason[k]
        cos = cos_inc[k]
        inten = cos
        if why == VALID and u_ghost[k] < outlier_prob:
            r = r + ghost_mm[k]
            inten = 0.5 * cos
        if why == VALID and u_drop[k] < dropout_prob:
            why = DROPOUT
        z = r * dir_z[k]
        if why == VALID and (z < z_start or z > z_end):
            why = NO_SURFACE
        if why == VALID:
            out_valid[k] = True
            out_xz[k, 0] = r * dir_x[k]
            out_xz[k, 1] = z
            out_intensity[k] = np.float32(inten)
        else:
            out_valid[k] = False
            out_xz[k, 0] = np.nan
            out_xz[k, 1] = np.nan
            out_intensity[k] = np.float32(0.0)


@njit(cache=True, nogil=True)
def measure_pass(seed, sensor, counter, kernel, lo, hi, range_mm, reason, cos_inc,
                 range_sigma, speckle_sigma, outlier_prob, dropout_prob, dir_x, dir_z,
                 z_start, z_end, out_xz, out_valid, out_intensity):
    """:func:`noise_draws` then :func:`apply_noise`: one profile from its trace in one call."""
    n = range_mm.shape[0]
    gauss, speckle = np.empty(n), np.empty(n)
    u_drop, u_ghost, ghost_mm = np.empty(n), np.empty(n), np.empty(n)
    noise_draws(seed, sensor, counter, kernel, lo, hi, gauss, speckle, u_drop, u_ghost,
                ghost_mm)
    apply_noise(range_mm, reason, cos_inc, gauss, speckle, u_drop, u_ghost, ghost_mm,
                range_sigma, speckle_sigma, outlier_prob, dropout_prob, dir_x, dir_z, z_start,
                z_end, out_xz, out_valid, out_intensity)
