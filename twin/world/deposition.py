"""Stochastic Gaussian cold-spray deposition onto the twin's height field, in the work object O.

Model (the paper's eq. for the coating distribution, sampled instead of integrated):

* **Mass.** Powder leaves the nozzle at ``feed_g_min / 60 * feed_factor`` [g/s]; with the powder
  density ``powder_density_g_cm3`` (CP-Ti 4.51 g/cm^3 = 0.00451 g/mm^3) that is a volume rate
  ``Q = feed_g_min / 60 / (density / 1000)`` [mm^3/s] (12 g/min of CP-Ti: 44.3 mm^3/s). It is
  carried by *packets* of fixed volume ``Q / packets_per_s``; a motion step of ``dt_s`` sends
  ``lam = packets_per_s * feed_factor * dt_s`` packets, rounded down or up at random so that
  the count is ``lam`` on average (the residence time of the executed motion sets how much
  lands where).
* **Plume.** Each packet leaves the nozzle exit (``standoff_mm + standoff_delta_mm`` behind the
  spot along the spray axis) displaced across the jet by an isotropic 2-D Gaussian of standard
  deviation ``sigma``, and travels along the axis to the current surface (exact ray cast).
  ``sigma = (nozzle_exit_mm / 2 + s * tan(plume_half_angle_deg)) / 2`` at standoff ``s``: the
  jet radius grows linearly from the exit radius with the divergence half-angle and is taken as
  two standard deviations (6.55 mm exit, 30 mm standoff, 5 deg: sigma = 2.95 mm). When
  ``plume_sigma_mm`` is set it is sigma at the nominal standoff and scales with the same law.
  A tilted spray therefore paints an elliptical footprint, stretched by ``1 / cos(theta)``.
  The displacements are not drawn independently: they are the successive points of one
  low-discrepancy (R2) sequence mapped through the plume's radial profile, carried over the
  model's whole life. A packet stands for a few hundred particles; drawn independently,
  packets would add shot noise of ``sqrt(h * v / A)`` over an area ``A`` after a build of
  height ``h`` with packet volume ``v`` (0.33 mm rms over 1 mm^2 after 50 mm), ten times a
  real 30 um powder's, and the twin's parts would grow bumps and pits 0.5-1 mm deep that no
  cell shows. Evenly placed packets cover the plume as the real powder does (a static spot
  matches the plume's profile to 0.3 % rms) while the motion, the surface and the twin's
  physics still set where and how much sticks.
* **Sticking.** The impact angle ``theta`` is the angle between the reversed jet and the surface
  normal, taken over ``NORMAL_STEP_MM`` = 1.5 mm either side of the hit: the macroscopic
  surface that an efficiency curve is measured against (a nozzle tilted over a flat coupon),
  not the slope of the packets' own roughness. Along each axis the two one-sided differences
  over that span are taken and the steeper kept: on a face they agree with a central
  difference, but a spike or ridge narrower than the span, which a central difference reads
  as flat, shows its flanks' slope. (With the central difference alone such a feature kept
  full efficiency, caught the tilted jet on its sides and put that volume on its own column:
  a 24 mm round column 40 layers tall grew a 0.75 mm^2 needle to 68 mm.) A normal over
  0.5 mm instead read the packets' roughness as impact angle, and the efficiency lost on its
  slopes fed it back: with independently drawn packets (before the R2 placement above) a wide
  flat raster (26 g/min, 30 mm/s, 2 mm spacing) roughened without bound (rms 0.14 mm after 8
  passes, 1.4 mm after 48) and stalled the twisted tower at about 40 mm. Over 1.5 mm the
  raster keeps 0.80 mm per pass for 72 passes, while walls, corners and the jet's own
  footprint (sigma about 3 mm) still set the angle (see ``benchmarks/tower_scale.py``).
  A packet adds ``zeta(theta) * efficiency_factor`` of its volume, with
  ``zeta(theta) = deposition_efficiency * cos^2(pi/2 * (theta / critical_angle)^2)`` for
  ``theta < critical_angle`` and 0 beyond: flat near normal impact (zeta(15 deg) = 0.98 zeta(0)
  at 75 deg critical angle), zeta(60 deg) = 0.29 zeta(0), smoothly to 0 with zero slope at the
  critical angle. Rebounding material is lost.
* **Steep faces.** Material striking a face steeper than the critical angle, relative to the
  jet, rebounds (the curve above is 0 there). Material that sticks adds to the column it
  struck: a packet that settled down a steeper face to where the surface is no steeper
  (the face building outward from its foot) was tried and left out, because on the twisted
  tower's flanks it gathered what stuck above into the first ledge and doubled the height of
  the flank spikes the validity check already finds there (see docs/twin-physics.md).
* **The twin's own physics.** ``physics`` (:class:`twin.world.twin_physics.TwinPhysics`,
  from the scenario's ``[twin_process]``) changes the curve's shape, the plume's radial profile
  (super-Gaussian), the deposit's porosity and makes efficiency depend on each packet's flight
  from the nozzle exit; without it the packets follow the nominal model above exactly.
* **Splat.** The stuck volume is spread over the 5 x 5 cells around the hit with normalised
  Gaussian weights (one cell sigma), so the height field gains exactly that volume.

All randomness (the sequence's start and the counts' rounding) is one SplitMix64 stream per
model seeded from ``seed``; same seed, same calls, same surface bit for bit.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from dm2.core.config import ProcessConfig
from twin.schema import TwinScenario
from twin.world import deposition_kernels as DK
from twin.world.heightfield import HeightField
from twin.world.twin_physics import NOMINAL, TwinPhysics

log = logging.getLogger(__name__)

NORMAL_STEP_MM = 1.5  # half-width of the impact-angle normal's one-sided differences [mm]


def volume_rate_mm3_s(process: ProcessConfig) -> float:
    """Powder volume leaving the nozzle at full feed [mm^3/s]."""
    return process.feed_g_min / 60.0 / (process.powder_density_g_cm3 / 1000.0)


def plume_sigma_mm(process: ProcessConfig, standoff_delta_mm: float = 0.0) -> float:
    """Standard deviation [mm] of the plume across the jet at the (changed) standoff."""
    tan_a = math.tan(math.radians(process.plume_half_angle_deg))
    radius = 0.5 * process.nozzle_exit_mm
    s = max(process.standoff_mm + standoff_delta_mm, 0.0)
    sigma = 0.5 * (radius + s * tan_a)
    if process.plume_sigma_mm is not None:
        sigma *= process.plume_sigma_mm / (0.5 * (radius + process.standoff_mm * tan_a))
    return sigma


def deposition_efficiency(process: ProcessConfig, theta_rad,
                          physics: TwinPhysics = NOMINAL) -> np.ndarray:
    """``zeta(theta)`` for impact angles ``theta_rad`` (array) [rad]: fraction that sticks
    (at the standoff; ``physics`` picks the curve)."""
    return process.deposition_efficiency * physics.relative_efficiency(
        theta_rad, process.critical_angle_deg)


class SprayModel:
    """The cold-spray jet: deposits packets onto a :class:`HeightField`.

    Parameters
    ----------
    process : ProcessConfig
    seed : int, seeds this model's packet stream
    physics : TwinPhysics, the twin's physics beyond the nominal model (default: none)

    Attributes
    ----------
    fed_volume_mm3 : float, total packet volume drawn so far (before sticking)
    deposited_volume_mm3 : float, total volume added to height fields so far (pores included)
    missed_packets : int, packets that missed the plate
    """

    def __init__(self, process: ProcessConfig, seed: int = 0, physics: TwinPhysics = NOMINAL):
        self.process = process
        self.physics = physics
        self._phys = physics.kernel_params(process.standoff_mm)
        self._radial = physics.radial_table()
        self.seed = int(seed)
        self._state = np.array([np.uint64(self.seed & 0xFFFFFFFFFFFFFFFF)], dtype=np.uint64)
        DK.next_u64(self._state)  # decorrelate small seeds
        # the packets' places across the jet: one R2 sequence for the model's whole life,
        # started at a seeded point
        self._seq = np.array([DK.uniform(self._state), DK.uniform(self._state)])
        self.v_packet_mm3 = volume_rate_mm3_s(process) / process.packets_per_s
        self._theta_c = math.radians(process.critical_angle_deg)
        self._sigma_cache: dict[float, float] = {0.0: plume_sigma_mm(process)}
        self.fed_volume_mm3 = 0.0
        self.deposited_volume_mm3 = 0.0
        self.missed_packets = 0

    @property
    def deposited_mass_g(self) -> float:
        """Mass [g] of the material added so far (its volume less the pores)."""
        return (self.deposited_volume_mm3 * (1.0 - self.physics.porosity)
                * self.process.powder_density_g_cm3 / 1000.0)

    def sigma_mm(self, standoff_delta_mm: float = 0.0) -> float:
        s = self._sigma_cache.get(standoff_delta_mm)
        if s is None:
            s = plume_sigma_mm(self.process, standoff_delta_mm)
            self._sigma_cache[standoff_delta_mm] = s
        return s

    def deposit(self, hf: HeightField, spot_O, axis_O, dt_s: float, feed_factor: float = 1.0,
                efficiency_factor: float = 1.0, standoff_delta_mm: float = 0.0) -> float:
        """Spray for ``dt_s`` seconds at ``spot_O (3,)`` [mm] along unit ``axis_O (3,)``.

        Mutates ``hf``; returns the deposited volume [mm^3].
        """
        spot = np.asarray(spot_O, dtype=np.float64)
        axis = np.asarray(axis_O, dtype=np.float64)
        if spot.shape != (3,) or axis.shape != (3,):
            raise ValueError(f"SprayModel.deposit: spot_O and axis_O must be (3,), "
                             f"got {spot.shape} and {axis.shape}")
        if dt_s < 0 or feed_factor < 0 or efficiency_factor < 0:
            raise ValueError("SprayModel.deposit: dt_s, feed_factor and efficiency_factor "
                             "must be non-negative")
        p = self.process
        lam = p.packets_per_s * feed_factor * dt_s
        vol, n, missed = DK.spray_step(
            _field_arrays(hf), self._state, self._seq, lam, spot, axis,
            self.sigma_mm(standoff_delta_mm), p.standoff_mm + standoff_delta_mm,
            p.deposition_efficiency * efficiency_factor, self._plume(hf))
        self.fed_volume_mm3 += n * self.v_packet_mm3
        self.deposited_volume_mm3 += vol
        self.missed_packets += missed
        return vol

    def deposit_samples(self, hf: HeightField, spot_O, axis_O, dt_s: float, spray_on=None,
                        feed_factor=None, efficiency_factor=None,
                        standoff_delta_mm=None) -> np.ndarray:
        """Deposit along executed-motion samples: ``spot_O (m, 3)``, ``axis_O (m, 3)``.

        Optional per-sample ``spray_on (m,)`` bool and factor arrays ``(m,)`` (or scalars).
        Returns the deposited volume per sample (m,) [mm^3].
        """
        plan = self.plan_samples(spot_O, axis_O, dt_s, spray_on, feed_factor,
                                 efficiency_factor, standoff_delta_mm)
        return self.deposit_plan(hf, plan, 0, plan.lam.size)

    def plan_samples(self, spot_O, axis_O, dt_s: float, spray_on=None, feed_factor=None,
                     efficiency_factor=None, standoff_delta_mm=None) -> SamplePlan:
        """The per-sample jet parameters of :meth:`deposit_samples`, worked out once for a
        whole motion so that :meth:`deposit_plan` can deposit it run by run."""
        spots = np.ascontiguousarray(spot_O, dtype=np.float64)
        axes = np.ascontiguousarray(axis_O, dtype=np.float64)
        if spots.ndim != 2 or spots.shape[1] != 3 or axes.shape != spots.shape:
            raise ValueError(f"SprayModel.deposit_samples: spot_O and axis_O must be (m, 3), "
                             f"got {spots.shape} and {axes.shape}")
        m = spots.shape[0]
        p = self.process
        on = np.ones(m, bool) if spray_on is None else np.broadcast_to(spray_on, (m,))
        ff = np.broadcast_to(1.0 if feed_factor is None else feed_factor, (m,))
        ef = np.broadcast_to(1.0 if efficiency_factor is None else efficiency_factor, (m,))
        sd = np.broadcast_to(0.0 if standoff_delta_mm is None else standoff_delta_mm, (m,))
        if np.any(ff < 0) or np.any(ef < 0) or dt_s < 0:
            raise ValueError("SprayModel.deposit_samples: dt_s and factors must be non-negative")
        # same operation order as :meth:`deposit`, so batching changes no bit of the result
        lam = np.where(on, p.packets_per_s * ff * dt_s, 0.0).astype(np.float64)
        sigma = np.array([self.sigma_mm(float(d)) for d in sd]) if np.any(sd != 0) else \
            np.full(m, self.sigma_mm(0.0))
        return SamplePlan(spots, axes, lam, sigma,
                          np.ascontiguousarray(p.standoff_mm + sd, dtype=np.float64),
                          np.ascontiguousarray(p.deposition_efficiency * ef, dtype=np.float64))

    def deposit_plan(self, hf: HeightField, plan: SamplePlan, a: int, b: int) -> np.ndarray:
        """Deposit samples ``a:b`` of ``plan``; the deposited volume per sample (b - a,)."""
        out = np.zeros(b - a)
        counts = np.zeros(2, dtype=np.int64)
        DK.spray_samples(_field_arrays(hf), self._state, self._seq, plan.lam[a:b],
                         plan.spots_O[a:b], plan.axes_O[a:b], plan.sigma_mm[a:b], plan.back_mm[a:b],
                         plan.zeta0[a:b], self._plume(hf), out, counts)
        self.fed_volume_mm3 += int(counts[0]) * self.v_packet_mm3
        self.deposited_volume_mm3 += float(out.sum())
        self.missed_packets += int(counts[1])
        return out

    def _plume(self, hf: HeightField) -> DK.Plume:
        """The fixed part of the spray as the kernels take it, on ``hf``'s node spacing."""
        return DK.Plume(self.v_packet_mm3, self._theta_c,
                        max(1, round(NORMAL_STEP_MM / hf.cell_mm)), self._phys, self._radial)


def _field_arrays(hf: HeightField) -> DK.FieldArrays:
    """``hf``'s arrays as the deposition kernels take them (views, updated in place)."""
    return DK.FieldArrays(hf._h, hf._bmax, hf._zmax, hf._dirty, hf.cell_mm, hf.thickness_mm)


@dataclass(frozen=True)
class SamplePlan:
    """Per-sample jet parameters for :meth:`SprayModel.deposit_plan` (made by ``plan_samples``).

    Attributes
    ----------
    spots_O, axes_O : (m, 3) float64 [mm] / unit, spray spot and axis in O
    lam : (m,) float64, expected packets per sample (0 where the spray is off)
    sigma_mm : (m,) float64 [mm], plume standard deviation
    back_mm : (m,) float64 [mm], nozzle exit distance behind the spot
    zeta0 : (m,) float64, normal-impact deposition efficiency (with its fault factor)
    """

    spots_O: np.ndarray
    axes_O: np.ndarray
    lam: np.ndarray
    sigma_mm: np.ndarray
    back_mm: np.ndarray
    zeta0: np.ndarray


def twin_process(scenario: TwinScenario) -> tuple[ProcessConfig, TwinPhysics]:
    """The twin's process (``[process]`` with ``[twin_process]`` applied, sigma and efficiency
    scaled) and its extra physics."""
    tp = scenario.twin_process
    proc = scenario.process.model_copy(update=tp.overrides())
    proc = ProcessConfig.model_validate({
        **proc.model_dump(),
        "plume_sigma_mm": plume_sigma_mm(proc) * tp.plume_sigma_factor,
        "deposition_efficiency": min(proc.deposition_efficiency * tp.efficiency_factor, 1.0)})
    physics = TwinPhysics(efficiency_curve=tp.efficiency_curve,
                          plateau_angle_deg=tp.plateau_angle_deg,
                          plume_exponent=tp.plume_exponent, porosity=tp.porosity,
                          standoff_efficiency_per_mm=tp.standoff_efficiency_per_mm,
                          efficiency_cos_exponent=tp.efficiency_cos_exponent,
                          logistic_k_per_rad=tp.logistic_k_per_rad,
                          logistic_phi0_rad=tp.logistic_phi0_rad)
    return proc, physics


def twin_spray_model(scenario: TwinScenario):
    """The :class:`twin.world.deposition.SprayModel` of the scenario's twin (its seed)."""
    proc, physics = twin_process(scenario)
    return SprayModel(proc, seed=scenario.seed, physics=physics)
