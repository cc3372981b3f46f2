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
from typing import NamedTuple

import numpy as np
from numba import njit

from twin.world.deposition_kernels import next_u64, uniform

# Reason codes, as in twin.profiler.sensor.
VALID = 0
NO_SURFACE = 1
DROPOUT = 7


class DrawStream(NamedTuple):
    """What fixes a profiler's random draws but the profile counter."""

    seed: int  # the scenario seed, a non-negative integer below 2**64
    sensor: int  # the profiler's index in SENSOR_IDS
    kernel: np.ndarray  # (2 * half + 1,) float64 unit-energy speckle kernel [-]
    ghost_lo: float  # [mm] ghost offsets along the ray are uniform in [ghost_lo, ghost_hi)
    ghost_hi: float  # [mm]


class Draws(NamedTuple):
    """One profile's random draws, each ``(n,)`` float64, in the order they are drawn."""

    gauss: np.ndarray  # standard normals of the range noise [-]
    speckle: np.ndarray  # unit-variance correlated normals of the speckle [-]
    u_drop: np.ndarray  # uniforms in [0, 1) deciding the dropouts
    u_ghost: np.ndarray  # uniforms in [0, 1) deciding the ghosts
    ghost_mm: np.ndarray  # ghost offsets along the ray [mm]


class SensorModel(NamedTuple):
    """A profiler's noise and output format: its ``[noise]`` and measuring range in S."""

    range_sigma: float  # [mm] Gaussian range noise along each ray
    speckle_sigma: float  # [mm] correlated speckle along each ray
    outlier_prob: float  # probability of a ghost beyond the surface [-]
    dropout_prob: float  # probability of a lost point [-]
    dir_x: np.ndarray  # (n,) float64 x_S of each unit ray direction in S
    dir_z: np.ndarray  # (n,) float64 z_S of each unit ray direction in S
    z_start: float  # [mm] measuring range along z_S, from
    z_end: float  # [mm] to


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
def noise_draws(stream, counter, draws):
    """Fill ``draws`` (:class:`Draws`, each ``(n,)``) of profile ``counter`` of the
    :class:`DrawStream` ``stream`` (see the module docstring for their order; either may be a
    plain tuple of its fields, as Python passes them: see :mod:`twin.profiler.scan_kernels`)."""
    stream, draws = DrawStream(*stream), Draws(*draws)
    gauss, speckle, u_drop, u_ghost, ghost_mm = draws
    kernel, lo, hi = stream.kernel, stream.ghost_lo, stream.ghost_hi
    n = gauss.shape[0]
    m = kernel.shape[0]
    state = stream_state(stream.seed, stream.sensor, counter)
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
def apply_noise(model, draws, range_mm, reason, cos_inc, out_xz, out_valid, out_intensity):
    """The sensor's noise and output format (:class:`SensorModel`) on the ``(n,)`` trace
    ``range_mm`` [mm], ``reason``, ``cos_inc``, from the profile's random ``draws``
    (:class:`Draws`): range noise and speckle along each ray, ghosts beyond the surface at half
    intensity, dropouts, the measuring range. Fills ``out_xz (n, 2)`` in S [mm],
    ``out_valid (n,)`` and ``out_intensity (n,) float32``; invalid points get NaN coordinates
    and zero intensity."""
    gauss, speckle, u_drop, u_ghost, ghost_mm = draws
    range_sigma, speckle_sigma = model.range_sigma, model.speckle_sigma
    outlier_prob, dropout_prob = model.outlier_prob, model.dropout_prob
    dir_x, dir_z, z_start, z_end = model.dir_x, model.dir_z, model.z_start, model.z_end
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
def measure_pass(stream, model, counter, range_mm, reason, cos_inc, out_xz, out_valid,
                 out_intensity):
    """:func:`noise_draws` of profile ``counter`` of ``stream`` then :func:`apply_noise` with
    ``model`` (:class:`SensorModel`; either may be a plain tuple of its fields, as Python
    passes them: see :mod:`twin.profiler.scan_kernels`): one profile from its trace in one
    call."""
    stream, model = DrawStream(*stream), SensorModel(*model)
    n = range_mm.shape[0]
    draws = Draws(np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n))
    noise_draws(stream, counter, draws)
    apply_noise(model, draws, range_mm, reason, cos_inc, out_xz, out_valid, out_intensity)
