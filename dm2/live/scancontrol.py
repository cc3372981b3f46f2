"""Micro-Epsilon scanCONTROL profilers driven directly through the vendor's Python wrapper.

Setup (Linux): install Micro-Epsilon's scanCONTROL Linux SDK (``libmescan`` and ``libllt``,
on top of aravis), then put its Python bindings on the path -- the SDK ships them as the
package ``pyllt`` (older releases: ``pylinllt``), a ctypes wrapper of ``libllt.so``::

    export PYTHONPATH=/opt/scanCONTROL-Linux-SDK/python_bindings:$PYTHONPATH
    python -c "import pyllt"          # must succeed before `dm2 monitor --live`

and list the sensors in the cell file::

    [[live.scancontrol]]
    sensor_id = "S1"
    serial = "218020093"              # the sensor's serial number (on its type label)
    resolution = 640
    exposure_us = 1000                # optional, a multiple of 10 us
    idle_us = 3000                    # optional, a multiple of 10 us

The wrapper is imported only when a cell file names scanCONTROL sensors; without it
:func:`load_wrapper` raises :class:`ScanControlUnavailable` with these instructions. Sensors on
another machine can instead run a bridge that speaks :mod:`dm2.live.tcp_frames`.

Per sensor, :class:`ScanControlSource` selects the sensor by its serial number, connects, checks
and sets the resolution, selects the ``PROFILE`` transfer format, sets internal triggering (and
exposure and idle time when given), registers a buffer callback and starts the transfer.
Every buffer the SDK hands over (``resolution * 64`` bytes: four reflections of 16 bytes per
point, the last 16 bytes of the buffer holding the profile's timestamp block) becomes one
:class:`~dm2.core.messages.Profile`:

- ``xz_S`` [mm] from ``convert_profile_2_values`` (first reflection; x along the line, z the
  distance from the sensor, the sensor frame of this project);
- points the sensor did not find -- reported with zero intensity or a zero distance -- are
  ``valid = False`` with NaN coordinates;
- ``intensity`` is the reflection's maximum (10 bit) scaled to 0..1;
- ``counter`` is the sensor's profile counter from the timestamp block (24 bit);
- ``stamp_s`` is the middle of the exposure from the timestamp block (``shutter_open`` and
  ``shutter_close``, seconds on the sensor's clock, which wraps every 128 s and is unwrapped
  here); the live runner's clock aligner maps it onto the robot's clock. With
  ``stamp="arrival"`` the host's arrival time is used instead (for sensors whose clock is not
  wanted), which the aligner treats the same way.

Buffers that do not convert count ``scancontrol_bad_profile`` in the inbox.

What the tests' fake wrapper (``tests/test_scancontrol.py``) assumes of the SDK, and where each
assumption comes from (no real sensor has been driven by this module yet):

- Sensor selection: the Linux SDK's ``get_device_interfaces(names, n)`` fills an array of
  C strings with the sensors it found, one per sensor, *identified by serial number* (the
  vendor's Linux Python examples pick ``available_interfaces[0]``; ROS drivers built on them
  match a configured ``serial`` against the listed names), and ``set_device_interface(h,
  name)`` takes one of those names. An IP address is what the Windows SDK's
  ``get_device_interfaces_fast`` returns (as integers), not the Linux one: the cell file
  therefore names ``serial``, matched exactly or as the end of a listed name.
- Exposure and idle time: ``set_feature(h, FEATURE_FUNCTION_SHUTTERTIME`` (newer wrappers:
  ``FEATURE_FUNCTION_EXPOSURE_TIME``) ``, value)`` and ``FEATURE_FUNCTION_IDLETIME``
  (``FEATURE_FUNCTION_IDLE_TIME``) take the time in *10 us steps*: the vendor's Python
  polling example sets exposure 100 and idle 3900 and then waits ``(idle + exposure) / 100000``
  seconds for a profile, i.e. 40 ms = 4000 x 10 us. The cell file gives microseconds; they are
  sent as ``us / 10`` and must be multiples of 10.
- Triggering: ``FEATURE_FUNCTION_TRIGGER`` value 0 is the internal trigger (the vendor's C++
  examples write ``0x00000000``; newer wrappers name it ``TRIG_INTERNAL``).
- Buffers: the callback ``buffer_cb_func(data, size, user_data)`` delivers ``resolution * 64``
  bytes in ``PROFILE`` format, the last 16 bytes the timestamp block, converted by
  ``convert_profile_2_values(buffer, size, resolution, PROFILE, scanner_type, 0, ...,
  intensity, ..., x, z, ...)`` and ``timestamp_2_time_and_count`` (the vendor's Linux
  callback examples); the return value's ``CONVERT_X``, ``CONVERT_Z`` and ``CONVERT_MAXIMUM``
  bits tell which arrays were filled. The fake encodes raw points as big-endian 16-bit words
  with a fixed x scale and z offset of its own: only the calling convention is the vendor's,
  not the raw encoding (the SDK's converter does that on real data).
"""

from __future__ import annotations

import ctypes as ct
import importlib
import logging
import time

import numpy as np

from dm2.core.messages import COUNTER_MODULO, MessageError, Profile
from dm2.live.inbox import Inbox

log = logging.getLogger(__name__)

WRAPPER_MODULES = ("pyllt", "pylinllt")
BYTES_PER_POINT = 64  # PROFILE format: 4 reflections x 16 bytes
TIMESTAMP_BYTES = 16  # the profile's trailing timestamp block
MAX_INTENSITY = 1023.0  # the reflection maximum is a 10-bit value
CLOCK_WRAP_S = 128.0  # the sensor's timestamp seconds field wraps after 128 s
TRIGGER_INTERNAL = 0  # FEATURE_FUNCTION_TRIGGER value for the sensor's own clock
TIME_STEP_US = 10  # exposure and idle time go to the sensor in 10 us steps
SETUP_HINT = ("install Micro-Epsilon's scanCONTROL Linux SDK and put its Python bindings "
              "(the `pyllt` package in the SDK's python_bindings folder) on PYTHONPATH; see "
              "dm2.live.scancontrol or README 'Live hardware'. Sensors on another machine can "
              "send the TCP profile protocol (dm2.live.tcp_frames) to live.profiles instead")


class ScanControlError(OSError):
    """A scanCONTROL sensor could not be set up (names the sensor and the SDK call)."""


class ScanControlUnavailable(ScanControlError):
    """The vendor's Python wrapper is not installed."""


def load_wrapper(names=WRAPPER_MODULES):
    """Import the scanCONTROL wrapper (the first of ``names`` that imports).

    Raises ScanControlUnavailable with the setup instructions when none does.
    """
    errors = []
    for name in names:
        try:
            return importlib.import_module(name)
        except ImportError as exc:  # also OSError from a missing libllt.so inside the wrapper
            errors.append(f"{name}: {exc}")
        except OSError as exc:
            errors.append(f"{name}: {exc}")
    raise ScanControlUnavailable("scanCONTROL sensors are listed in live.scancontrol but the "
                                 f"vendor's Python wrapper is not available ({'; '.join(errors)})"
                                 f": {SETUP_HINT}")


class ClockUnwrapper:
    """Turn the sensor's 128 s wrapping timestamps into a continuous time [s]."""

    def __init__(self, period_s: float = CLOCK_WRAP_S):
        self.period_s = float(period_s)
        self._last: float | None = None
        self._offset = 0.0

    def __call__(self, t_s: float) -> float:
        if self._last is not None and t_s < self._last - self.period_s / 2:
            self._offset += self.period_s
        elif self._last is not None and t_s > self._last + self.period_s / 2:
            return t_s + self._offset - self.period_s  # late, from before the wrap
        self._last = t_s
        return t_s + self._offset


class ProfileConverter:
    """Raw ``PROFILE`` buffers of one sensor -> :class:`~dm2.core.messages.Profile`.

    Parameters
    ----------
    llt : the wrapper module
    sensor_id : "S1".."S3"
    resolution : int, points per profile
    scanner_type : the value ``get_llt_type`` reported
    """

    def __init__(self, llt, sensor_id: str, resolution: int, scanner_type):
        self.llt = llt
        self.sensor_id = sensor_id
        self.resolution = int(resolution)
        self.scanner_type = scanner_type
        self.buffer_bytes = self.resolution * BYTES_PER_POINT
        n = self.resolution
        self._x = (ct.c_double * n)()
        self._z = (ct.c_double * n)()
        self._intensity = (ct.c_ushort * n)()
        self._null_us = ct.POINTER(ct.c_ushort)()
        self._null_ui = ct.POINTER(ct.c_uint)()
        self._unwrap = ClockUnwrapper()

    def convert(self, data: bytes, arrival_s: float | None = None) -> Profile:
        """One profile from one raw buffer; ``arrival_s`` replaces the sensor's stamp.

        Raises MessageError naming the sensor when the buffer does not convert.
        """
        llt, n = self.llt, self.resolution
        if len(data) != self.buffer_bytes:
            raise MessageError(f"scanCONTROL {self.sensor_id}: buffer of {len(data)} bytes, "
                               f"expected {self.buffer_bytes} ({n} points x "
                               f"{BYTES_PER_POINT})")
        buf = (ct.c_ubyte * len(data)).from_buffer_copy(data)
        ret = llt.convert_profile_2_values(
            buf, len(data), n, llt.TProfileConfig.PROFILE, self.scanner_type, 0,
            self._null_us, self._intensity, self._null_us, self._x, self._z,
            self._null_ui, self._null_ui)
        if ret & llt.CONVERT_X == 0 or ret & llt.CONVERT_Z == 0 or \
                ret & llt.CONVERT_MAXIMUM == 0:
            raise MessageError(f"scanCONTROL {self.sensor_id}: convert_profile_2_values "
                               f"returned {ret}")
        x = np.frombuffer(self._x, dtype=np.float64, count=n).copy()
        z = np.frombuffer(self._z, dtype=np.float64, count=n).copy()
        inten = np.frombuffer(self._intensity, dtype=np.uint16, count=n).astype(np.float32)
        valid = (inten > 0) & (z != 0.0) & np.isfinite(x) & np.isfinite(z)
        xz = np.column_stack([x, z])
        xz[~valid] = np.nan
        stamp_s, counter = self.timestamp(data)
        if arrival_s is not None:
            stamp_s = arrival_s
        return Profile(self.sensor_id, stamp_s, counter % COUNTER_MODULO, xz, valid,
                       np.minimum(inten / MAX_INTENSITY, 1.0))

    def timestamp(self, data: bytes) -> tuple[float, int]:
        """``(mid-exposure time [s], unwrapped; profile counter)`` of a raw buffer."""
        block = (ct.c_ubyte * TIMESTAMP_BYTES).from_buffer_copy(data[-TIMESTAMP_BYTES:])
        opened, closed, count = ct.c_double(0.0), ct.c_double(0.0), ct.c_uint(0)
        self.llt.timestamp_2_time_and_count(block, ct.byref(opened), ct.byref(closed),
                                            ct.byref(count), ct.POINTER(ct.c_ushort)())
        return self._unwrap(0.5 * (opened.value + closed.value)), int(count.value)


class ScanControlSource:
    """One scanCONTROL sensor feeding an :class:`Inbox` (source name ``"scancontrol"``).

    Parameters
    ----------
    inbox : where profiles go
    sensor_id : "S1".."S3"
    serial : the sensor's serial number, as ``get_device_interfaces`` lists it
    resolution : points per profile (one the sensor offers)
    llt : the wrapper module (default: :func:`load_wrapper`)
    stamp : "sensor" (timestamp block) or "arrival" (host clock at the callback)
    exposure_us, idle_us : optional exposure and idle time [us] to set (multiples of 10 us:
        the sensor takes them in 10 us steps)
    """

    name = "scancontrol"

    def __init__(self, inbox: Inbox, sensor_id: str, serial: str, resolution: int = 640, *,
                 llt=None, stamp: str = "sensor", exposure_us: int | None = None,
                 idle_us: int | None = None):
        if stamp not in ("sensor", "arrival"):
            raise ValueError(f"ScanControlSource.stamp: 'sensor' or 'arrival', got {stamp!r}")
        self.inbox = inbox
        self.sensor_id = sensor_id
        self.serial = str(serial)
        for name, value in (("exposure_us", exposure_us), ("idle_us", idle_us)):
            if value is not None and (int(value) != value or value < 0
                                      or int(value) % TIME_STEP_US):
                raise ValueError(f"scanCONTROL {sensor_id}: {name} = {value}: the sensor takes "
                                 f"times in {TIME_STEP_US} us steps; give a multiple of "
                                 f"{TIME_STEP_US}")
        self.resolution = int(resolution)
        self.stamp = stamp
        self.exposure_us = exposure_us
        self.idle_us = idle_us
        self.llt = load_wrapper() if llt is None else llt
        self.received = 0
        self.converter: ProfileConverter | None = None
        self._handle = None
        self._callback = None  # keeps the ctypes callback alive while the SDK holds it
        self._transferring = False
        self.address = (self.serial, self.sensor_id)

    def _check(self, ret: int, call: str) -> int:
        if ret < 1:
            raise ScanControlError(f"scanCONTROL {self.sensor_id} (serial {self.serial}): "
                                   f"{call} failed with {ret}")
        return ret

    def start(self) -> ScanControlSource:
        """Connect, configure and start the profile transfer (ScanControlError on failure)."""
        llt = self.llt
        try:
            self._handle = h = llt.create_llt_device()
            names = [ct.create_string_buffer(16) for _ in range(6)]
            listed = (ct.c_char_p * 6)(*map(ct.addressof, names))
            found = self._check(llt.get_device_interfaces(listed, len(names)),
                                "get_device_interfaces")
            offered = [b.value.decode(errors="replace") for b in names[:found]]
            chosen = [n for n in offered if n == self.serial or n.endswith(self.serial)]
            if len(chosen) != 1:
                raise ScanControlError(f"scanCONTROL {self.sensor_id}: serial number "
                                       f"{self.serial} not found (the SDK lists {offered})")
            self._check(llt.set_device_interface(h, chosen[0].encode()),
                        "set_device_interface")
            self._check(llt.connect(h), "connect")
            scanner_type = ct.c_int(0)
            self._check(llt.get_llt_type(h, ct.byref(scanner_type)), "get_llt_type")
            resolutions = (ct.c_uint * 4)()
            n_res = self._check(llt.get_resolutions(h, resolutions, len(resolutions)),
                                "get_resolutions")
            if self.resolution not in list(resolutions)[:n_res]:
                raise ScanControlError(f"scanCONTROL {self.sensor_id}: resolution "
                                       f"{self.resolution} not offered (sensor offers "
                                       f"{list(resolutions)[:n_res]})")
            self._check(llt.set_resolution(h, self.resolution), "set_resolution")
            self._check(llt.set_profile_config(h, llt.TProfileConfig.PROFILE),
                        "set_profile_config")
            self._check(llt.set_feature(h, llt.FEATURE_FUNCTION_TRIGGER, TRIGGER_INTERNAL),
                        "set_feature(trigger)")
            for value, names, what in (
                    (self.exposure_us, ("FEATURE_FUNCTION_EXPOSURE_TIME",
                                        "FEATURE_FUNCTION_SHUTTERTIME"), "exposure"),
                    (self.idle_us, ("FEATURE_FUNCTION_IDLE_TIME", "FEATURE_FUNCTION_IDLETIME"),
                     "idle time")):
                if value is not None:
                    feature = next(getattr(llt, n) for n in names if hasattr(llt, n))
                    self._check(llt.set_feature(h, feature, int(value) // TIME_STEP_US),
                                f"set_feature({what}, {int(value) // TIME_STEP_US} x 10 us)")
            self.converter = ProfileConverter(llt, self.sensor_id, self.resolution,
                                              scanner_type.value)
            self._callback = llt.buffer_cb_func(self._on_buffer)
            self._check(llt.register_buffer_callback(h, self._callback, None),
                        "register_buffer_callback")
            self._check(llt.transfer_profiles(h, llt.TTransferProfileType.NORMAL_TRANSFER, 1),
                        "transfer_profiles")
            self._transferring = True
        except BaseException:
            self.close()
            raise
        log.info("scanCONTROL %s streaming from serial %s (%d points)", self.sensor_id,
                 self.serial, self.resolution)
        return self

    def _on_buffer(self, data, size, _user_data) -> None:
        """The SDK's buffer callback (its thread): convert and queue; never raises."""
        arrival = time.monotonic()
        self.received += 1
        try:
            raw = ct.string_at(data, size)
            p = self.converter.convert(raw, arrival if self.stamp == "arrival" else None)
        except (MessageError, ValueError, TypeError) as exc:
            self.inbox.drop("scancontrol_bad_profile")
            log.debug("%s", exc)
            return
        self.inbox.put(p, self.name, arrival)

    def close(self) -> None:
        """Stop the transfer, disconnect and release the device (errors only logged)."""
        h, self._handle = self._handle, None
        if h is None:
            return
        llt = self.llt
        steps = [("disconnect", lambda: llt.disconnect(h)), ("del_device",
                                                              lambda: llt.del_device(h))]
        if self._transferring:
            steps.insert(0, ("transfer_profiles(stop)", lambda: llt.transfer_profiles(
                h, llt.TTransferProfileType.NORMAL_TRANSFER, 0)))
        self._transferring = False
        for call, step in steps:
            try:
                ret = step()
                if ret is not None and ret < 1:
                    log.warning("scanCONTROL %s: %s returned %s", self.sensor_id, call, ret)
            except Exception:  # noqa: BLE001 - closing must go on with the other steps
                log.exception("scanCONTROL %s: %s failed", self.sensor_id, call)

    def __enter__(self) -> ScanControlSource:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
