"""Make a truncated MCAP recording (a crash's ``.part``) readable and indexed again.

The file is read record by record (:class:`mcap.stream_reader.StreamReader`, chunks
decompressed and checked against their CRCs) up to the first damaged or missing record; every
complete schema, channel, message, attachment and metadata record before that point is copied,
unchanged, into a new file with chunk indexes and a summary, so ordinary MCAP readers (and
:func:`dm2.io.recording.read_recording`) open it. The new file says it was recovered: a
``dm2.recovered`` metadata record (:mod:`dm2.io.mcap_integrity`), which a run on it reports.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from dm2.io.mcap_integrity import (
    READ_ERRORS,
    RECOVERED_METADATA,
    attachment_crc_holds,
    recovered_record,
)
from dm2.io.recording import MCAP_MAGIC

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RecoveryResult:
    """What :func:`recover_recording` copied.

    Attributes
    ----------
    out_path : the rewritten recording
    messages : int, messages copied
    attachments : int, attachments copied
    complete : bool, True if the input ended properly (nothing was cut off)
    last_stamp_s : float [s], log time of the newest message copied (NaN if none)
    note : str, what was lost ("nothing lost", "last 0.4 s lost", ...)
    """

    out_path: Path
    messages: int
    attachments: int
    complete: bool
    last_stamp_s: float
    note: str = ""


def default_output(path: Path) -> Path:
    """``run.mcap.part`` -> ``run.mcap``; ``run.mcap`` -> ``run.recovered.mcap``."""
    if path.name.endswith(".part"):
        return path.with_name(path.name[: -len(".part")])
    return path.with_name(f"{path.stem}.recovered{path.suffix or '.mcap'}")


def _end_stamp_ns(path: Path) -> int | None:
    """The newest message time the file's own summary gives, if it has a sound one."""
    from dm2.io.mcap_integrity import summary_intact

    try:
        with open(path, "rb") as f:
            if not summary_intact(f):
                return None
            f.seek(0)
            summary = make_reader(f).get_summary()
        if summary is None or summary.statistics is None:
            return None
        return int(summary.statistics.message_end_time)
    except READ_ERRORS:
        return None


class _Copy:
    """The records of one recording copied into a new writer, ids mapped."""

    def __init__(self, writer: Writer):
        self.writer = writer
        self.schema_ids: dict[int, int] = {}
        self.channel_ids: dict[int, int] = {}
        self.messages = self.attachments = 0
        self.bad_attachments: list[str] = []
        self.last_ns: int | None = None

    def add(self, rec, raw_record) -> None:
        w = self.writer
        if isinstance(rec, Schema):
            if rec.id not in self.schema_ids:
                self.schema_ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
        elif isinstance(rec, Channel):
            if rec.id not in self.channel_ids:
                self.channel_ids[rec.id] = w.register_channel(
                    rec.topic, rec.message_encoding, self.schema_ids.get(rec.schema_id, 0),
                    rec.metadata)
        elif isinstance(rec, Message):
            cid = self.channel_ids.get(rec.channel_id)
            if cid is None:
                return
            w.add_message(cid, log_time=rec.log_time, data=rec.data,
                          publish_time=rec.publish_time, sequence=rec.sequence)
            self.messages += 1
            self.last_ns = rec.log_time if self.last_ns is None else max(self.last_ns,
                                                                         rec.log_time)
        elif isinstance(rec, Attachment):
            if not attachment_crc_holds(raw_record()):
                self.bad_attachments.append(rec.name)
                return
            w.add_attachment(create_time=rec.create_time, log_time=rec.log_time,
                             name=rec.name, media_type=rec.media_type, data=rec.data)
            self.attachments += 1
        elif isinstance(rec, Metadata):
            name = rec.name if rec.name != RECOVERED_METADATA else RECOVERED_METADATA + ".earlier"
            w.add_metadata(name, dict(rec.metadata))


def recover_recording(path: str | Path, out_path: str | Path | None = None) -> RecoveryResult:
    """Copy every complete, intact record of ``path`` into a proper MCAP file at ``out_path``.

    Reading stops at the first record that is cut off, cannot be decompressed or fails its CRC
    (:mod:`dm2.io.mcap_integrity`); an attachment that fails its CRC is left out. The new
    file carries a ``dm2.recovered`` metadata record: the original file and size, where the
    reading stopped and why, the newest stamp kept and, where the original's summary says
    how far it went, the seconds lost.

    Raises FileNotFoundError / ValueError (naming the file) when ``path`` is missing, is not
    an MCAP file at all or is cut off before anything could be recovered (nothing is written
    then); the output is written as ``<out>.recovering`` and renamed when complete, and
    removed whatever stops the copy.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: recording not found")
    out = Path(out_path) if out_path is not None else default_output(path)
    if out.resolve() == path.resolve():
        raise ValueError(f"{path}: the recovered file must not overwrite its input")
    with open(path, "rb") as f:
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise ValueError(f"{path}: not an MCAP file (bad magic bytes)")
    part = out.with_name(out.name + ".recovering")
    try:
        result, fields = _copy_into(path, part)
        if not result.complete and result.messages == 0 and result.attachments == 0:
            raise ValueError(f"{path}: nothing to recover: the file is cut off or damaged "
                             f"before its first complete message or attachment")
        part.replace(out)
    finally:
        part.unlink(missing_ok=True)
    log.info("recovered %s -> %s: %d messages, %d attachments%s", path, out, result.messages,
             result.attachments, "" if result.complete else f" ({fields['note']})")
    return RecoveryResult(out, result.messages, result.attachments, result.complete,
                          result.last_stamp_s, fields["note"])


def _copy_into(path: Path, part: Path) -> tuple[RecoveryResult, dict[str, str]]:
    complete, reason, stopped_at = True, "", None
    size = path.stat().st_size
    with open(path, "rb") as src, open(part, "wb") as dst:
        writer = Writer(dst, compression=CompressionType.ZSTD)
        copy = _Copy(writer)
        profile, started = "", False
        prev_end = src.tell()

        def raw_record(start=None, end=None):
            here = src.tell()
            src.seek(start)
            data = src.read(end - start)
            src.seek(here)
            return data

        records = StreamReader(src, validate_crcs=True).records
        while True:
            try:  # only reading is damage; an error writing the copy is not caught here
                rec = next(records)
            except StopIteration:
                break
            except READ_ERRORS as exc:
                complete, reason, stopped_at = False, str(exc) or type(exc).__name__, prev_end
                log.info("%s: stopped at a damaged or missing record (%s)", path, reason)
                break
            end = src.tell()
            if not started:
                profile = getattr(rec, "profile", "")
                writer.start(profile=profile, library="dm2 recover")
                started = True
            else:
                copy.add(rec, lambda s=prev_end, e=end: raw_record(s, e))
            prev_end = end
        if not started:
            writer.start(profile=profile, library="dm2 recover")
        last_s = copy.last_ns / 1e9 if copy.last_ns is not None else float("nan")
        end_ns = _end_stamp_ns(path)
        lost_s = (max(0.0, (end_ns - copy.last_ns) / 1e9)
                  if end_ns is not None and copy.last_ns is not None else None)
        if complete:
            note = "nothing lost"
        elif lost_s is not None:
            note = f"last {lost_s:.1f} s lost"
        else:
            note = "the rest after the last stamp kept lost (its length is not known)"
        if copy.bad_attachments:
            note += "; attachments left out (CRC): " + ", ".join(copy.bad_attachments)
        fields = {"original_file": path.name, "original_bytes": str(size),
                  "complete": "true" if complete and not copy.bad_attachments else "false",
                  "stopped_at_byte": "" if stopped_at is None else str(stopped_at),
                  "reason": reason[:200], "last_stamp_s": f"{last_s:.6f}",
                  "lost_s": "" if lost_s is None else f"{lost_s:.3f}", "note": note}
        writer.add_metadata(RECOVERED_METADATA, recovered_record(fields))
        writer.finish()
    ok = complete and not copy.bad_attachments
    return RecoveryResult(part, copy.messages, copy.attachments, ok, last_s, note), fields
