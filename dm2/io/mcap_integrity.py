"""What an MCAP recording's checksums cover, and reading its records only where they hold.

Every dm2 recording is chunked (:class:`dm2.io.recording_writer.RecordingWriter`), so each
message lies in a chunk whose header holds the CRC-32 of its uncompressed records. The
reader checks:

- every chunk's CRC once it is decompressed (a chunk that cannot be decompressed, or whose
  records differ from what was written, ends the reading there, like a truncation);
- the summary's CRC (the footer's ``summary_crc``: channels, chunk indexes, attachment
  indexes); a summary that fails it is not used, and the file is read linearly;
- each attachment's own CRC (``scenario.toml``, ``toolpath.csv``, ``calibration.toml``); an
  attachment that fails it is left out and reported;
- in a linear read, the data section's CRC at its end (``DataEnd``): damage outside every
  chunk (a message index, the header) is reported after every message was read;
- the recovery record that ``dm2 recover`` writes carries a CRC of its own fields.

Not covered: bytes that no reader uses (a chunk header's start and end times, the message
indexes, in an indexed read) are not checked there; they do not change what is read.
"""

from __future__ import annotations

import io
import struct
import zlib

from mcap.exceptions import McapError

try:  # the codecs MCAP chunks may use; their errors are damage, not crashes
    from zstandard import ZstdError
except ImportError:  # pragma: no cover
    ZstdError = McapError

# everything a damaged recording can make the mcap reader raise
READ_ERRORS = (McapError, EOFError, ValueError, struct.error, OSError, ZstdError, KeyError,
               IndexError, RuntimeError, MemoryError, OverflowError)

RECOVERED_METADATA = "dm2.recovered"
_FOOTER_BYTES = 1 + 8 + 8 + 8 + 4  # opcode, length, summary_start, summary_offset_start, crc
_MAGIC_BYTES = 8


class SeekTracker:
    """A read-only file that remembers where it was last sought to (the chunk being read);
    a plain object, not an ``io`` class, so no wrapper the reader makes can close it."""

    def __init__(self, f):
        self._f = f
        self.last_seek = 0

    def read(self, n: int = -1) -> bytes:
        return self._f.read(n)

    def seekable(self) -> bool:
        return True

    def readable(self) -> bool:
        return True

    def seek(self, pos: int, whence: int = io.SEEK_SET) -> int:
        out = self._f.seek(pos, whence)
        self.last_seek = out
        return out

    def tell(self) -> int:
        return self._f.tell()


def summary_intact(f) -> bool:
    """Whether the footer's summary CRC holds (True where the writer left it 0: unchecked)."""
    size = f.seek(0, io.SEEK_END)
    if size < _MAGIC_BYTES * 2 + _FOOTER_BYTES:
        return False
    f.seek(size - _MAGIC_BYTES - _FOOTER_BYTES)
    footer = f.read(_FOOTER_BYTES)
    summary_start, _offsets, crc = struct.unpack("<QQI", footer[9:])
    if crc == 0 or summary_start == 0:
        return True
    end = size - _MAGIC_BYTES - 4
    if not 0 < summary_start <= end:
        return False
    f.seek(summary_start)
    return zlib.crc32(f.read(end - summary_start)) == crc


def attachment_crc_holds(raw: bytes) -> bool:
    """Whether an attachment record (opcode to CRC, as in the file) matches its CRC."""
    if len(raw) < 13:
        return False
    (crc,) = struct.unpack("<I", raw[-4:])
    return crc == 0 or zlib.crc32(raw[9:-4]) == crc


def indexed_attachments(f, summary) -> tuple[dict[str, bytes], list[str]]:
    """The attachments the summary indexes, each read and checked against its CRC:
    ``({name: data}, [names that failed])``."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Attachment

    good, bad = {}, []
    for idx in summary.attachment_indexes:
        try:
            f.seek(idx.offset)
            raw = f.read(idx.length)
            ok = len(raw) == idx.length and attachment_crc_holds(raw)
            rec = Attachment.read(ReadDataStream(io.BytesIO(raw[9:]))) if ok else None
        except READ_ERRORS:
            ok, rec = False, None
        if ok and rec.name == idx.name:
            good[rec.name] = bytes(rec.data)
        else:
            bad.append(idx.name)
    return good, bad


def indexed_metadata(reader) -> dict[str, dict[str, str]]:
    """The metadata records an indexed reader finds (name -> fields; none if unreadable)."""
    try:
        return {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    except READ_ERRORS:
        return {}


def linear_extras(f) -> tuple[dict[str, bytes], list[str], dict[str, dict[str, str]]]:
    """Attachments and metadata found reading the file record by record up to the first
    unreadable one, each attachment checked against its CRC: ``({name: data}, [names that
    failed], {metadata name: fields})``."""
    from mcap.records import Attachment, Metadata
    from mcap.stream_reader import StreamReader

    good, bad, meta = {}, [], {}
    f.seek(0)
    start = f.tell()
    try:
        for rec in StreamReader(f, emit_chunks=True).records:
            end = f.tell()
            if isinstance(rec, Attachment):
                f.seek(start)
                raw = f.read(end - start)
                f.seek(end)
                if attachment_crc_holds(raw):
                    good[rec.name] = bytes(rec.data)
                else:
                    bad.append(rec.name)
            elif isinstance(rec, Metadata):
                meta[rec.name] = dict(rec.metadata)
            start = end
    except READ_ERRORS:
        pass
    return good, bad, meta


def _fields_crc(fields: dict[str, str]) -> str:
    text = "\n".join(f"{k}={fields[k]}" for k in sorted(fields) if k != "crc32")
    return f"{zlib.crc32(text.encode()):08x}"


def recovered_record(fields: dict[str, str]) -> dict[str, str]:
    """The ``dm2.recovered`` metadata: ``fields`` with a CRC of them (``crc32``)."""
    return {**fields, "crc32": _fields_crc(fields)}


def recovery_note(metadata: dict[str, str]) -> dict:
    """A ``dm2.recovered`` record read back: its fields, with ``intact`` False where its CRC
    fails (then its figures cannot be trusted)."""
    out: dict = {k: v for k, v in metadata.items() if k != "crc32"}
    out["intact"] = metadata.get("crc32") == _fields_crc(metadata)
    return out
