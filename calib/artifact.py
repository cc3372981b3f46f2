"""The calibration artifact: a plate carrying spheres of known radius, held by the robot.

Why spheres
-----------
A laser line cutting a sphere of radius ``r`` measures points whose distance to the sphere
centre is exactly ``r``. In the laser plane the points lie on a circle of radius
``rho = sqrt(r**2 - h**2)``, where ``h`` is the distance of the centre from the plane; one
profile therefore locates the sphere centre in the sensor frame ``S`` up to the sign of
``y_S``. The robot reports where that centre is in the base frame ``B``, so every profile is a
3D point correspondence, and three or more correspondences that are not collinear fix all six
degrees of freedom of ``T_B_S``. With three or more spheres the artifact's own pose on the
flange ``T_F_A`` is observable too, once the flange rotates between poses.

Degenerate pose sets (detected by :mod:`calib.solver`, never silently solved):

- every observed sphere centre lies on one line in ``B`` (e.g. one sphere moved along a
  line): rotation about that line is free;
- only one sphere position is seen (one pose, one sphere): all rotations about it are free;
- every cut passes through the sphere centres (``h = 0``): the offset of the laser plane
  along ``y_S`` is only constrained to second order;
- co-estimating the mount from pure flange translations: ``T_F_A`` and ``T_B_S`` trade off.

Artifact TOML format
--------------------
::

    schema = 1
    name = "four_spheres"
    description = "free text"
    work_object = true      # frame A is the work object O (mounted like the substrate plate)

    [mount]                 # nominal pose of A on the flange, T_F_A; optional when
    translation_mm = [-60.0, -60.0, 150.0]   # work_object = true (then the cell's T_F_O)
    euler_zyx_deg = [0.0, 0.0, 0.0]

    [plate]                 # the plate occupies [0, Lx] x [0, Ly] x [-thickness, 0] in A
    size_mm = [120.0, 120.0, 6.0]
    touch_mark_mm = [20.0, 20.0, 3.0]   # optional: seat point of the nozzle touch-off cone
                                        # (the exit centre sits there; calib.touch_off)

    [certificate]           # optional: expanded uncertainties of the certified geometry
    radius_mm = 0.002       # sphere radii
    position_mm = 0.005     # sphere centres, per axis

    [[spheres]]             # one table per sphere
    center_mm = [52.0, 54.0, 16.0]   # in A
    radius_mm = 8.0
    post_radius_mm = 2.0    # vertical post from the plate top to the sphere (0: none)
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from dm2.core.config import ConfigError, format_validation_error, read_toml
from dm2.core.frames import from_euler_deg
from dm2.core.tolerances import NEAR_ZERO, SAME_POINT_MM

ARTIFACT_SCHEMA = 1


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class _Mount(_Model):
    translation_mm: tuple[float, float, float]
    euler_zyx_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)


class _Plate(_Model):
    size_mm: tuple[float, float, float] = (120.0, 120.0, 6.0)
    touch_mark_mm: tuple[float, float, float] | None = None


class _Certificate(_Model):
    radius_mm: float = Field(0.0, ge=0)
    position_mm: float = Field(0.0, ge=0)


class _Sphere(_Model):
    center_mm: tuple[float, float, float]
    radius_mm: float = Field(gt=0)
    post_radius_mm: float = Field(0.0, ge=0)


class _ArtifactFile(_Model):
    schema_: int = Field(ARTIFACT_SCHEMA, alias="schema")
    name: str
    description: str = ""
    work_object: bool = False
    mount: _Mount | None = None
    plate: _Plate = _Plate()
    certificate: _Certificate = _Certificate()
    spheres: tuple[_Sphere, ...] = Field(min_length=1)

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True,
                              allow_inf_nan=False)


@dataclass(frozen=True)
class Artifact:
    """A sphere artifact in its own frame ``A``.

    Attributes
    ----------
    name : str
    T_F_A : (4, 4) float64, nominal pose of the artifact on the flange [mm]; None until
        :meth:`with_mount` resolves it for a work-object artifact without ``[mount]``
    centers_A : (k, 3) float64 [mm], sphere centres
    radii_mm : (k,) float64 [mm]
    post_radii_mm : (k,) float64 [mm], radius of the post under each sphere (0: none)
    plate_size_mm : (3,) float64 [mm], (Lx, Ly, thickness)
    work_object : bool, True when ``A`` is the work object ``O`` (so ``T_F_A`` is ``T_F_O``)
    touch_mark_A : (3,) float64 [mm] or None, seat point of the nozzle touch-off cone
    radius_uncertainty_mm, position_uncertainty_mm : float, the certificate's uncertainties
    """

    name: str
    T_F_A: np.ndarray | None
    centers_A: np.ndarray
    radii_mm: np.ndarray
    post_radii_mm: np.ndarray
    plate_size_mm: np.ndarray
    work_object: bool = False
    touch_mark_A: np.ndarray | None = None
    radius_uncertainty_mm: float = 0.0
    position_uncertainty_mm: float = 0.0

    def __post_init__(self):
        c = np.asarray(self.centers_A, dtype=np.float64).reshape(-1, 3)
        r = np.asarray(self.radii_mm, dtype=np.float64).reshape(-1)
        p = np.asarray(self.post_radii_mm, dtype=np.float64).reshape(-1)
        if not (c.shape[0] == r.size == p.size) or c.shape[0] == 0:
            raise ValueError("Artifact: centers_A, radii_mm and post_radii_mm disagree in length")
        if np.any(r <= 0) or np.any(p < 0) or np.any(p >= r):
            raise ValueError("Artifact: radii must be > 0 and posts thinner than their sphere")
        if np.any(c[:, 2] - r < 0):
            k = int(np.argmax(c[:, 2] - r < 0))
            raise ValueError(f"Artifact: sphere {k} reaches below the plate top (z_A < 0)")
        d = np.linalg.norm(c[:, None] - c[None], axis=2) - (r[:, None] + r[None])
        np.fill_diagonal(d, 1.0)
        if np.any(d <= 0):
            i, j = np.argwhere(d <= 0)[0]
            raise ValueError(f"Artifact: spheres {i} and {j} overlap")
        values = [("centers_A", c), ("radii_mm", r), ("post_radii_mm", p),
                  ("plate_size_mm", np.asarray(self.plate_size_mm, dtype=np.float64))]
        if self.T_F_A is not None:
            T = np.asarray(self.T_F_A, dtype=np.float64)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise ValueError("Artifact.T_F_A: expected a finite (4, 4) transform")
            values.append(("T_F_A", T))
        if self.touch_mark_A is not None:
            m = np.asarray(self.touch_mark_A, dtype=np.float64).reshape(-1)
            if m.size != 3 or not np.all(np.isfinite(m)):
                raise ValueError("Artifact.touch_mark_A: expected 3 finite numbers")
            values.append(("touch_mark_A", m))
        for name, val in values:
            val = val.copy()
            val.setflags(write=False)
            object.__setattr__(self, name, val)

    def with_mount(self, T_F_O: np.ndarray) -> Artifact:
        """This artifact with its mount resolved: a work-object artifact without ``[mount]``
        sits where the plate sits (``T_F_O``); any other keeps its own mount."""
        if self.T_F_A is not None:
            return self
        return replace(self, T_F_A=np.asarray(T_F_O, dtype=np.float64))

    @property
    def n_spheres(self) -> int:
        return int(self.radii_mm.size)

    def raycast_A(self, origins_A: np.ndarray, dirs_A: np.ndarray) -> tuple[np.ndarray,
                                                                            np.ndarray]:
        """First hit of rays with the artifact (spheres, posts, plate) in frame ``A``.

        Parameters
        ----------
        origins_A, dirs_A : (n, 3) float64 [mm], ray origins and unit directions

        Returns
        -------
        t_mm : (n,) float64 [mm], distance to the first hit (inf: miss)
        feature : (n,) int64, sphere index hit, -2 post or plate, -1 miss
        """
        o = np.asarray(origins_A, dtype=np.float64)
        d = np.asarray(dirs_A, dtype=np.float64)
        k = self.n_spheres
        t_all = np.full((o.shape[0], 2 * k + 1), np.inf)
        for i in range(k):
            t_all[:, i] = ray_sphere(o, d, self.centers_A[i], self.radii_mm[i])
            if self.post_radii_mm[i] > 0:
                base = np.array([self.centers_A[i, 0], self.centers_A[i, 1], 0.0])
                t_all[:, k + i] = ray_cylinder(o, d, base, np.array([0.0, 0.0, 1.0]),
                                               self.post_radii_mm[i], self.centers_A[i, 2])
        t_all[:, 2 * k] = ray_box(o, d, np.array([0.0, 0.0, -self.plate_size_mm[2]]),
                                  np.array([self.plate_size_mm[0], self.plate_size_mm[1], 0.0]))
        j = np.argmin(t_all, axis=1)
        t = t_all[np.arange(o.shape[0]), j]
        feature = np.where(j < k, j, -2)
        feature[~np.isfinite(t)] = -1
        return t, feature


def ray_sphere(o: np.ndarray, d: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    """Distance (n,) [mm] along unit rays to the first positive hit of a sphere (inf: miss)."""
    oc = o - center
    b = np.einsum("ij,ij->i", oc, d)
    c = np.einsum("ij,ij->i", oc, oc) - radius * radius
    disc = b * b - c
    ok = disc >= 0
    s = np.sqrt(np.where(ok, disc, 0.0))
    t0, t1 = -b - s, -b + s
    t = np.where(t0 > SAME_POINT_MM, t0, np.where(t1 > SAME_POINT_MM, t1, np.inf))
    return np.where(ok, t, np.inf)


def ray_cylinder(o: np.ndarray, d: np.ndarray, base: np.ndarray, axis: np.ndarray,
                 radius: float, length: float) -> np.ndarray:
    """Distance (n,) [mm] to the first hit of a finite open cylinder's side (inf: miss).

    The cylinder runs from ``base`` along unit ``axis`` for ``length`` mm.
    """
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    oc = o - base
    d_perp = d - np.outer(d @ a, a)
    o_perp = oc - np.outer(oc @ a, a)
    A = np.einsum("ij,ij->i", d_perp, d_perp)
    B = np.einsum("ij,ij->i", o_perp, d_perp)
    C = np.einsum("ij,ij->i", o_perp, o_perp) - radius * radius
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = B * B - A * C
        ok = (disc >= 0) & (A > NEAR_ZERO)
        s = np.sqrt(np.where(ok, disc, 0.0))
        out = np.full(o.shape[0], np.inf)
        for sign in (1.0, -1.0):  # far root first, near root overwrites
            t = np.where(ok, (-B + sign * s) / np.where(A > NEAR_ZERO, A, 1.0), np.inf)
            h = (oc @ a) + t * (d @ a)
            hit = ok & (t > SAME_POINT_MM) & (h >= 0) & (h <= length)
            out = np.where(hit & (t < out), t, out)
    return out


def ray_box(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distance (n,) [mm] to the first positive hit of an axis-aligned box (inf: miss)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    t1 = np.nan_to_num(t1, nan=-np.inf)
    t2 = np.nan_to_num(t2, nan=np.inf)
    tmin = np.max(np.minimum(t1, t2), axis=1)
    tmax = np.min(np.maximum(t1, t2), axis=1)
    hit = (tmax >= np.maximum(tmin, 0.0)) & (tmax > SAME_POINT_MM)
    t = np.where(tmin > SAME_POINT_MM, tmin, tmax)
    return np.where(hit, t, np.inf)


def parse_artifact(data: dict, source: str = "<artifact>") -> Artifact:
    """Validate a parsed artifact TOML dict; errors name ``source`` and the field."""
    try:
        f = _ArtifactFile.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(source, exc)) from None
    if f.schema_ != ARTIFACT_SCHEMA:
        raise ConfigError(f"{source}: field 'schema': unsupported artifact schema {f.schema_}")
    if f.mount is None and not f.work_object:
        raise ConfigError(f"{source}: field 'mount': missing (only a work_object artifact may "
                          "omit it and sit where the plate sits)")
    T_F_A = None
    if f.mount is not None:
        T_F_A = from_euler_deg(f.mount.translation_mm, f.mount.euler_zyx_deg, "ZYX")
    try:
        return Artifact(
            name=f.name,
            T_F_A=T_F_A,
            centers_A=np.array([s.center_mm for s in f.spheres]),
            radii_mm=np.array([s.radius_mm for s in f.spheres]),
            post_radii_mm=np.array([s.post_radius_mm for s in f.spheres]),
            plate_size_mm=np.array(f.plate.size_mm),
            work_object=f.work_object,
            touch_mark_A=None if f.plate.touch_mark_mm is None else np.array(
                f.plate.touch_mark_mm),
            radius_uncertainty_mm=f.certificate.radius_mm,
            position_uncertainty_mm=f.certificate.position_mm,
        )
    except ValueError as exc:
        raise ConfigError(f"{source}: field 'spheres': {exc}") from None


def load_artifact(path: str | Path) -> Artifact:
    """Read an artifact TOML file (format in this module's docstring). Raises ConfigError."""
    path = Path(path)
    return parse_artifact(read_toml(path, "artifact file"), str(path))
