"""TCP profile protocol for sensor-side bridges: the frame format, its encoder and its parser.

Wire format (little endian). Each frame is a ``uint32`` length ``L`` (bytes that follow) and::

    offset  type        field
    0       4 bytes     magic  b"DM2P"
    4       uint16      version (1)
    6       uint8       sensor number (1 -> "S1", 2 -> "S2", 3 -> "S3")
    7       uint8       flags (0; reserved)
    8       uint32      counter (24-bit profile counter, < 2**24)
    12      float64     stamp [s] on the sensor's clock
    20      uint32      n, point count
    24      n float32   x_S [mm]   (NaN where the sensor reported no point)
    ..      n float32   z_S [mm]   (NaN where the sensor reported no point)
    ..      n uint16    intensity (0..65535 -> 0..1)
    ..      uint32      CRC-32 (zlib) of everything from the magic to the intensities

so ``L = 28 + 10 n``. A bridge connects to the monitor (loopback by default) and streams frames;
it reconnects after a dropped connection (the listening source and a client:
:mod:`dm2.live.tcp_profiles`). The parser survives any byte stream: it resynchronises
on the magic and counts what it drops (``oversized_frame``, ``truncated_frame`` -- a frame cut
short by the next frame's start or by the end of the connection --, ``corrupt_frame`` -- bad
magic, version, sizes or CRC --, ``bad_frame_field`` -- a frame that does not make a valid
profile).
"""

from __future__ import annotations

import logging
import struct
import zlib

import numpy as np

from dm2.core.messages import COUNTER_MODULO, SENSOR_IDS, MessageError, Profile

log = logging.getLogger(__name__)

MAGIC = b"DM2P"
VERSION = 1
_LEN = struct.Struct("<I")
_HEAD = struct.Struct("<4sHBBIdI")  # magic, version, sensor, flags, counter, stamp, n
_CRC = struct.Struct("<I")
FIXED_BYTES = _HEAD.size + _CRC.size  # 28
MAX_FRAME_BYTES = FIXED_BYTES + 10 * 4096


def encode_frame(p: Profile) -> bytes:
    """One length-prefixed frame of a profile (float32 coordinates, uint16 intensity)."""
    n = p.n_points
    xz = np.where(p.valid[:, None], p.xz_S, np.nan).astype("<f4")
    inten = np.clip(np.nan_to_num(p.intensity, nan=0.0), 0.0, 1.0)
    body = b"".join([
        _HEAD.pack(MAGIC, VERSION, SENSOR_IDS.index(p.sensor_id) + 1, 0, p.counter,
                   p.stamp_s, n),
        np.ascontiguousarray(xz[:, 0]).tobytes(), np.ascontiguousarray(xz[:, 1]).tobytes(),
        np.round(inten * 65535.0).astype("<u2").tobytes()])
    return _LEN.pack(len(body) + _CRC.size) + body + _CRC.pack(zlib.crc32(body))


def decode_body(body: bytes) -> Profile:
    """A profile from one frame body (after the length, CRC already checked).

    Raises MessageError naming the bad field.
    """
    magic, version, sensor, _flags, counter, stamp_s, n = _HEAD.unpack_from(body)
    if magic != MAGIC or version != VERSION:
        raise MessageError(f"profile frame: bad magic {magic!r} or version {version}")
    if len(body) != _HEAD.size + 10 * n:
        raise MessageError(f"profile frame: {len(body)} bytes do not hold {n} points")
    if not 1 <= sensor <= len(SENSOR_IDS):
        raise MessageError(f"profile frame: sensor number {sensor} not in 1..{len(SENSOR_IDS)}")
    if counter >= COUNTER_MODULO:
        raise MessageError(f"profile frame: counter {counter} exceeds 24 bits")
    if not np.isfinite(stamp_s) or stamp_s < 0:
        raise MessageError(f"profile frame: stamp {stamp_s!r} is not a finite time >= 0")
    o = _HEAD.size
    x = np.frombuffer(body, "<f4", n, o).astype(np.float64)
    z = np.frombuffer(body, "<f4", n, o + 4 * n).astype(np.float64)
    inten = np.frombuffer(body, "<u2", n, o + 8 * n).astype(np.float32) / np.float32(65535.0)
    xz = np.column_stack([x, z])
    valid = ~(np.isnan(x) | np.isnan(z))
    return Profile(SENSOR_IDS[sensor - 1], stamp_s, counter, xz, valid, inten)


class FrameParser:
    """Incremental parser of the frame stream of one connection.

    ``feed(data)`` returns the profiles completed by ``data``; drops are counted in
    :attr:`dropped` (dict reason -> count). ``close()`` counts a partial frame at the end.
    """

    def __init__(self, max_frame_bytes: int = MAX_FRAME_BYTES):
        self.max_frame_bytes = int(max_frame_bytes)
        self.dropped: dict[str, int] = {}
        self._buf = bytearray()
        self._resyncing = False  # bytes at the head are leftovers of a frame already counted

    def _drop(self, reason: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1
        self._resyncing = True

    def _resync(self, start: int) -> None:
        """Discard bytes up to the next magic found at or after ``start + 1`` (minus length)."""
        k = self._buf.find(MAGIC, start + 1)
        if k < 0:  # keep a tail that could be the start of a magic
            del self._buf[: max(len(self._buf) - (len(MAGIC) - 1) - _LEN.size, 0)]
        else:
            del self._buf[: max(k - _LEN.size, 0)]

    def feed(self, data: bytes) -> list[Profile]:
        self._buf += data
        out: list[Profile] = []
        buf = self._buf
        while len(buf) >= _LEN.size + len(MAGIC):
            (length,) = _LEN.unpack_from(buf)
            if buf[_LEN.size: _LEN.size + len(MAGIC)] != MAGIC:
                if not self._resyncing:
                    self._drop("corrupt_frame")
                self._resync(_LEN.size)
                continue
            if length > self.max_frame_bytes:
                self._drop("oversized_frame")
                self._resync(_LEN.size)
                continue
            if length < FIXED_BYTES:
                self._drop("corrupt_frame")
                self._resync(_LEN.size)
                continue
            end = _LEN.size + length
            if len(buf) < end:
                # a new frame starting inside this one's extent means this one was cut short
                nxt = buf.find(MAGIC, _LEN.size + 1)
                if nxt >= 0 and self._plausible_start(nxt):
                    self._drop("truncated_frame")
                    del buf[: nxt - _LEN.size]
                    continue
                break
            body = bytes(buf[_LEN.size: end - _CRC.size])
            (crc,) = _CRC.unpack_from(buf, end - _CRC.size)
            if zlib.crc32(body) != crc:
                nxt = buf.find(MAGIC, _LEN.size + 1, end)
                if nxt >= 0 and self._plausible_start(nxt):
                    self._drop("truncated_frame")
                    del buf[: nxt - _LEN.size]
                else:
                    self._drop("corrupt_frame")
                    self._resync(_LEN.size)
                continue
            del buf[:end]
            self._resyncing = False
            try:
                out.append(decode_body(body))
            except (MessageError, ValueError, struct.error) as exc:
                self._drop("bad_frame_field")
                log.debug("profile frame dropped: %s", exc)
        return out

    def _plausible_start(self, magic_at: int) -> bool:
        """A magic at ``magic_at`` preceded by a sane length field starts a frame."""
        if magic_at < _LEN.size:
            return False
        (length,) = _LEN.unpack_from(self._buf, magic_at - _LEN.size)
        return FIXED_BYTES <= length <= self.max_frame_bytes and (length - FIXED_BYTES) % 10 == 0

    def close(self) -> None:
        """End of the connection: a partial frame left in the buffer counts truncated."""
        if self._buf and not self._resyncing:
            self._drop("truncated_frame")
            self._buf.clear()
