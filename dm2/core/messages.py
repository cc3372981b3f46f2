"""The pipeline's input contracts: identical for the twin, recordings and live hardware.

Every contract is a frozen dataclass of numpy arrays, validated on construction. A message that
fails validation raises :class:`MessageError`, whose text names the message and the field.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dm2.core.tolerances import UNIT_NORM_TOL

SENSOR_IDS = ("S1", "S2", "S3")
COUNTER_MODULO = 1 << 24  # scanCONTROL profile counters are 24 bit
TOOLPATH_KINDS = ("infill", "edge", "skip", "overhang")
KIND_CODE = {k: i for i, k in enumerate(TOOLPATH_KINDS)}
_EYE3 = np.eye(3)


class MessageError(ValueError):
    """A message or contract failed validation; the text names the message and the field."""


def _array(name: str, field_name: str, value, dtype, shape, finite: bool = False) -> np.ndarray:
    try:
        arr = np.ascontiguousarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise MessageError(
            f"{name}.{field_name}: cannot convert to {np.dtype(dtype)}: {exc}") from exc
    if len(shape) != arr.ndim or any(
            s is not None and s != a for s, a in zip(shape, arr.shape, strict=True)):
        raise MessageError(f"{name}.{field_name}: expected shape {shape}, got {arr.shape}")
    if finite and arr.size and not np.all(np.isfinite(arr)):
        raise MessageError(f"{name}.{field_name}: contains NaN or infinite values")
    arr.setflags(write=False)
    return arr


def _scalar(name: str, field_name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise MessageError(f"{name}.{field_name}: not a number: {value!r}") from exc
    if not np.isfinite(v):
        raise MessageError(f"{name}.{field_name}: not finite: {value!r}")
    return v


@dataclass(frozen=True)
class Profile:
    """One laser line from one profiler, in the sensor's frame.

    Attributes
    ----------
    sensor_id : str, one of ``SENSOR_IDS``
    stamp_s : float [s], acquisition time on the cell clock
    counter : int or None, 24-bit profile counter (wraps at 2**24); None where the source
        carries none (rosbag2 recordings): duplicates are then recognised by (sensor, stamp)
    xz_S : (n, 2) float64 [mm], points in the laser plane (y_S = 0); may hold NaN where invalid
    valid : (n,) bool, False where the sensor reported no point
    intensity : (n,) float32, reflected intensity (0..1)
    """

    sensor_id: str
    stamp_s: float
    counter: int | None
    xz_S: np.ndarray
    valid: np.ndarray
    intensity: np.ndarray

    def __post_init__(self):
        if self.sensor_id not in SENSOR_IDS:
            raise MessageError(f"Profile.sensor_id: {self.sensor_id!r} not in {SENSOR_IDS}")
        object.__setattr__(self, "stamp_s", _scalar("Profile", "stamp_s", self.stamp_s))
        if self.counter is not None:
            c = int(self.counter)
            if not 0 <= c < COUNTER_MODULO:
                raise MessageError(f"Profile.counter: {c} outside the 24-bit range")
            object.__setattr__(self, "counter", c)
        xz = _array("Profile", "xz_S", self.xz_S, np.float64, (None, 2))
        n = xz.shape[0]
        valid = _array("Profile", "valid", self.valid, bool, (n,))
        inten = _array("Profile", "intensity", self.intensity, np.float32, (n,))
        object.__setattr__(self, "xz_S", xz)
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "intensity", inten)

    @classmethod
    def trusted(cls, sensor_id: str, stamp_s: float, counter: int, xz_S: np.ndarray,
                valid: np.ndarray, intensity: np.ndarray) -> Profile:
        """A profile from a producer that already holds valid arrays, without re-validating.

        Only for producers that build the arrays themselves (the twin's profilers): the caller
        guarantees ``sensor_id`` in ``SENSOR_IDS``, a finite ``stamp_s``, ``counter`` in the
        24-bit range, ``xz_S`` a C-contiguous (n, 2) float64, ``valid`` a (n,) bool and
        ``intensity`` a (n,) float32 array that nobody writes afterwards. The result equals
        ``Profile(...)`` of the same arguments (the arrays are made read-only in place).
        Anything read from outside goes through the constructor.
        """
        self = object.__new__(cls)
        for arr in (xz_S, valid, intensity):
            arr.flags.writeable = False
        object.__setattr__(self, "sensor_id", sensor_id)
        object.__setattr__(self, "stamp_s", float(stamp_s))
        object.__setattr__(self, "counter", int(counter))
        object.__setattr__(self, "xz_S", xz_S)
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "intensity", intensity)
        return self

    @property
    def n_points(self) -> int:
        return int(self.xz_S.shape[0])


@dataclass(frozen=True)
class RobotState:
    """Robot controller state (as ABB EGM reports it).

    Attributes
    ----------
    stamp_s : float [s]
    seq : int, controller sequence number
    joints_rad : (6,) float64 [rad]
    T_B_F : (4, 4) float64, flange pose in the robot base [mm]
    """

    stamp_s: float
    seq: int
    joints_rad: np.ndarray
    T_B_F: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "stamp_s", _scalar("RobotState", "stamp_s", self.stamp_s))
        object.__setattr__(self, "seq", int(self.seq))
        j = _array("RobotState", "joints_rad", self.joints_rad, np.float64, (6,), finite=True)
        T = _array("RobotState", "T_B_F", self.T_B_F, np.float64, (4, 4), finite=True)
        if T[3, 0] != 0.0 or T[3, 1] != 0.0 or T[3, 2] != 0.0 or T[3, 3] != 1.0:
            raise MessageError("RobotState.T_B_F: last row must be [0, 0, 0, 1]")
        R = T[:3, :3]
        if float(np.abs(R.T @ R - _EYE3).max()) > UNIT_NORM_TOL:
            raise MessageError("RobotState.T_B_F: rotation part is not orthonormal")
        object.__setattr__(self, "joints_rad", j)
        object.__setattr__(self, "T_B_F", T)

    @classmethod
    def trusted(cls, stamp_s: float, seq: int, joints_rad: np.ndarray,
                T_B_F: np.ndarray) -> RobotState:
        """A state from a producer that already holds valid arrays, without re-validating.

        Only for producers that build the arrays themselves (the twin's executed motion): the
        caller guarantees a finite ``stamp_s``, ``joints_rad`` a finite C-contiguous (6,)
        float64 and ``T_B_F`` a finite C-contiguous (4, 4) float64 rigid transform. The result
        equals ``RobotState(stamp_s, seq, joints_rad, T_B_F)`` (read-only views of the arrays,
        ``float`` stamp, ``int`` seq; arrays that are already read-only are taken as they are).
        Anything read from outside goes through the constructor.
        """
        self = object.__new__(cls)
        j, T = joints_rad, T_B_F
        if j.flags.writeable:
            j = j.view()
            j.flags.writeable = False
        if T.flags.writeable:
            T = T.view()
            T.flags.writeable = False
        object.__setattr__(self, "stamp_s", float(stamp_s))
        object.__setattr__(self, "seq", int(seq))
        object.__setattr__(self, "joints_rad", j)
        object.__setattr__(self, "T_B_F", T)
        return self


@dataclass(frozen=True)
class LayerMark:
    """The controller's report that layer ``layer`` starts at ``stamp_s``."""

    stamp_s: float
    layer: int

    def __post_init__(self):
        object.__setattr__(self, "stamp_s", _scalar("LayerMark", "stamp_s", self.stamp_s))
        if int(self.layer) < 0:
            raise MessageError(f"LayerMark.layer: negative layer {self.layer}")
        object.__setattr__(self, "layer", int(self.layer))


@dataclass(frozen=True)
class Calibration:
    """The cell's calibration as the pipeline is given it.

    Attributes
    ----------
    T_B_S : dict sensor id -> (4, 4) float64, each profiler's pose in the robot base [mm]
    T_F_O : (4, 4) float64, work object (plate corner) on the flange [mm]
    T_B_N : (4, 4) float64, nozzle exit in the robot base; +z_N is the spray direction [mm]
    """

    T_B_S: dict
    T_F_O: np.ndarray
    T_B_N: np.ndarray

    def __post_init__(self):
        poses = {}
        for sid, T in dict(self.T_B_S).items():
            if sid not in SENSOR_IDS:
                raise MessageError(f"Calibration.T_B_S: unknown sensor id {sid!r}")
            poses[sid] = _array("Calibration", f"T_B_S[{sid}]", T, np.float64, (4, 4), True)
        object.__setattr__(self, "T_B_S", poses)
        for name in ("T_F_O", "T_B_N"):
            val = _array("Calibration", name, getattr(self, name), np.float64, (4, 4), True)
            object.__setattr__(self, name, val)


@dataclass(frozen=True)
class Toolpath:
    """A continuous (C3D-style) toolpath in the work-object frame ``O``.

    Attributes
    ----------
    position_O : (n, 3) float64 [mm], target point on the surface being sprayed
    axis_O : (n, 3) float64, unit spray direction (from nozzle towards the surface)
    speed_mm_s : (n,) float64 [mm/s], programmed speed of the move *into* point i
    kind : (n,) int8, index into ``TOOLPATH_KINDS`` (infill, edge, skip, overhang)
    layer : (n,) int32, layer index (0-based)
    spray_on : (n,) bool, powder flowing on the move into point i
    zone_mm : (n,) float64 [mm], corner blending radius at point i
    """

    position_O: np.ndarray
    axis_O: np.ndarray
    speed_mm_s: np.ndarray
    kind: np.ndarray
    layer: np.ndarray
    spray_on: np.ndarray
    zone_mm: np.ndarray
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        pos = _array("Toolpath", "position_O", self.position_O, np.float64, (None, 3), True)
        n = pos.shape[0]
        axis = _array("Toolpath", "axis_O", self.axis_O, np.float64, (n, 3), True)
        if n and not np.allclose(np.linalg.norm(axis, axis=1), 1.0, atol=UNIT_NORM_TOL):
            raise MessageError("Toolpath.axis_O: rows must be unit vectors")
        speed = _array("Toolpath", "speed_mm_s", self.speed_mm_s, np.float64, (n,), True)
        if n and np.any(speed <= 0):
            raise MessageError("Toolpath.speed_mm_s: speeds must be positive")
        kind = _array("Toolpath", "kind", self.kind, np.int8, (n,))
        if n and (kind.min() < 0 or kind.max() >= len(TOOLPATH_KINDS)):
            raise MessageError(f"Toolpath.kind: codes must index {TOOLPATH_KINDS}")
        layer = _array("Toolpath", "layer", self.layer, np.int32, (n,))
        if n and (layer.min() < 0 or np.any(np.diff(layer) < 0)):
            raise MessageError("Toolpath.layer: must be >= 0 and non-decreasing")
        spray = _array("Toolpath", "spray_on", self.spray_on, bool, (n,))
        zone = _array("Toolpath", "zone_mm", self.zone_mm, np.float64, (n,), True)
        if n and np.any(zone < 0):
            raise MessageError("Toolpath.zone_mm: must be >= 0")
        for name, val in (("position_O", pos), ("axis_O", axis), ("speed_mm_s", speed),
                          ("kind", kind), ("layer", layer), ("spray_on", spray), ("zone_mm", zone)):
            object.__setattr__(self, name, val)

    def __len__(self) -> int:
        return int(self.position_O.shape[0])

    @property
    def n_layers(self) -> int:
        return int(self.layer.max()) + 1 if len(self) else 0

    def kind_names(self) -> np.ndarray:
        """Kinds as strings, (n,) object array."""
        return np.asarray(TOOLPATH_KINDS, dtype=object)[self.kind]

    def select(self, mask: np.ndarray) -> Toolpath:
        """A toolpath with only the rows where ``mask`` is True."""
        return Toolpath(self.position_O[mask], self.axis_O[mask], self.speed_mm_s[mask],
                        self.kind[mask], self.layer[mask], self.spray_on[mask],
                        self.zone_mm[mask], dict(self.meta))
