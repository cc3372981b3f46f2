"""The twin's own deposition physics: the scenario's ``[twin_process]`` resolved against
``[process]``.

The monitor predicts the near-net part from the nominal ``[process]`` with its own model
(``dm2.reference``). A real cell never matches that model, so the twin deposits with physics of
its own (:class:`TwinPhysics`, used by :class:`twin.world.deposition.SprayModel`):

* ``[process]`` keys repeated in ``[twin_process]`` override the nominal values;
* ``plume_sigma_factor`` and ``efficiency_factor`` scale the resulting plume sigma and
  normal-impact efficiency;
* ``efficiency_curve`` (+ ``plateau_angle_deg``; the ``logistic`` curve's
  ``logistic_k_per_rad`` and ``logistic_phi0_rad``): the efficiency's fall with impact angle,
  times ``cos(theta) ** efficiency_cos_exponent`` (the twin's own exponent: never the one in
  ``[process]``, which describes the monitor's model of the curve);
* ``plume_exponent`` ``p``: packets leave the nozzle with the radial density
  ``exp(-(r/a)^p / 2)`` across the jet, ``a`` chosen so that the per-axis rms stays sigma
  (``p = 2``: the Gaussian). ``s = (r/a)^p / 2`` is then Gamma(2/p)-distributed, so the radius
  is drawn from its inverse CDF, tabulated once per exponent;
* ``porosity``: the deposit holds that volume fraction of pores, so the stuck mass stands
  ``1 / (1 - porosity)`` times taller than at full density;
* ``standoff_efficiency_per_mm``: efficiency changes by this fraction per mm that a packet's
  flight from the nozzle exit to the surface exceeds the twin's standoff (a surface that grew
  short stands farther from the nozzle; a standoff fault moves the nozzle).

:data:`NOMINAL` is the nominal model exactly (what a bare ``SprayModel(process)`` uses);
``twin.world.deposition.twin_process`` resolves a scenario's sections into the twin's process
and physics, ``twin.world.deposition.twin_spray_model`` builds its spray model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.special import expit

# index = the kernels' CURVE_* code
CURVES = ("cos2", "cos", "linear", "plateau", "logistic")
RADIAL_TABLE_NODES = 4096  # quantile intervals of the tabulated inverse radial CDF
RADIAL_TAIL_QUANTILE = 1.0 - 1e-7  # the table's last node (the tail beyond is cut)


@dataclass(frozen=True)
class TwinPhysics:
    """Deposition physics the nominal model lacks (defaults: the nominal model itself).

    Attributes
    ----------
    efficiency_curve : one of :data:`CURVES`
    plateau_angle_deg : float [deg], where the "plateau" curve starts to fall
    plume_exponent : float, radial super-Gaussian exponent (2 = Gaussian)
    porosity : float, pore volume fraction of the deposit
    standoff_efficiency_per_mm : float [1/mm], relative efficiency per mm of extra flight
    efficiency_cos_exponent : float, the curve times ``cos(theta)`` to this power
    logistic_k_per_rad, logistic_phi0_rad : float [1/rad], [rad], the "logistic" curve
        ``expit(k (phi - phi0)) / expit(k (pi/2 - phi0))``, ``phi = pi/2 - theta`` the spray
        angle between jet and surface (the shape fitted to cold-spray deposition experiments
        in published deposition simulators); no cut at the critical angle, 0 from grazing
    """

    efficiency_curve: str = "cos2"
    plateau_angle_deg: float = 30.0
    plume_exponent: float = 2.0
    porosity: float = 0.0
    standoff_efficiency_per_mm: float = 0.0
    efficiency_cos_exponent: float = 0.0
    logistic_k_per_rad: float = 9.0
    logistic_phi0_rad: float = 0.61

    def __post_init__(self):
        if self.efficiency_curve not in CURVES:
            raise ValueError(f"TwinPhysics.efficiency_curve: {self.efficiency_curve!r} is not "
                             f"one of {', '.join(CURVES)}")
        if not 1.0 <= self.plume_exponent <= 8.0:
            raise ValueError(f"TwinPhysics.plume_exponent: {self.plume_exponent} outside [1, 8]")
        if not 0.0 <= self.porosity < 0.5:
            raise ValueError(f"TwinPhysics.porosity: {self.porosity} outside [0, 0.5)")
        if not 0.0 <= self.efficiency_cos_exponent <= 6.0:
            raise ValueError(f"TwinPhysics.efficiency_cos_exponent: "
                             f"{self.efficiency_cos_exponent} outside [0, 6]")

    @property
    def bulk_factor(self) -> float:
        """Deposit volume per volume of stuck powder at full density."""
        return 1.0 / (1.0 - self.porosity)

    def kernel_params(self, standoff_mm: float) -> np.ndarray:
        """The PHYS_* array of :mod:`twin.world.deposition_kernels` (``standoff_mm``: the
        spray distance at which the standoff term is neutral)."""
        return np.array([CURVES.index(self.efficiency_curve),
                         math.radians(self.plateau_angle_deg), self.bulk_factor,
                         self.standoff_efficiency_per_mm, standoff_mm,
                         self.efficiency_cos_exponent, self.logistic_k_per_rad,
                         self.logistic_phi0_rad], dtype=np.float64)

    def radial_table(self) -> np.ndarray:
        """Inverse CDF of the radius across the jet in sigmas (empty for the Gaussian)."""
        return _radial_table(float(self.plume_exponent))

    def relative_efficiency(self, theta_rad, critical_angle_deg: float) -> np.ndarray:
        """The curve's relative efficiency at impact angles ``theta_rad`` (array) [rad]."""
        theta = np.asarray(theta_rad, dtype=np.float64)
        tc = math.radians(critical_angle_deg)
        if self.efficiency_curve == "cos2":
            x = np.clip(theta / tc, 0.0, 1.0)
            z = np.cos(0.5 * np.pi * x * x) ** 2
        elif self.efficiency_curve == "cos":
            z = np.cos(theta)
        elif self.efficiency_curve == "linear":
            z = 1.0 - theta / tc
        elif self.efficiency_curve == "logistic":
            k, phi0 = self.logistic_k_per_rad, self.logistic_phi0_rad
            z = expit(k * (0.5 * np.pi - theta - phi0)) / expit(k * (0.5 * np.pi - phi0))
            tc = 0.5 * np.pi  # no cut at the critical angle: 0 from grazing
        else:
            tp = math.radians(self.plateau_angle_deg)
            z = np.where(theta <= tp, 1.0, (tc - theta) / (tc - tp))
        if self.efficiency_cos_exponent != 0.0:
            z = z * np.cos(np.clip(theta, 0.0, 0.5 * np.pi)) ** self.efficiency_cos_exponent
        return np.where(theta < tc, z, 0.0)


NOMINAL = TwinPhysics()


@lru_cache(maxsize=16)
def _radial_table(p: float) -> np.ndarray:
    if p == 2.0:
        return np.zeros(0)
    from scipy.special import gamma, gammaincinv

    k = 2.0 / p
    # per-axis variance of r (cos phi): E[r^2] / 2 = a^2 2^(2/p) Gamma(4/p) / Gamma(2/p) / 2
    a = math.sqrt(2.0 * gamma(k) / (2.0 ** k * gamma(2.0 * k)))
    q = np.linspace(0.0, 1.0, RADIAL_TABLE_NODES + 1)
    q[-1] = RADIAL_TAIL_QUANTILE
    s = gammaincinv(k, q)
    table = a * (2.0 * s) ** (1.0 / p)
    table.setflags(write=False)
    return table
