"""Make a truncated MCAP recording (a crash's ``.part``) readable and indexed again.

The file is read record by record (:class:`mcap.stream_reader.StreamReader`, chunks
decompressed) up to the first damaged or missing record; every complete schema, channel,
message, attachment and metadata record before that point is copied, unchanged, into a new
file with chunk indexes and a summary, so ordinary MCAP readers (and
:func:`dm2.io.recording.read_recording`) open it.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass
from pathlib import Path

from mcap.exceptions import McapError
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

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
    """

    out_path: Path
    messages: int
    attachments: int
    complete: bool
    last_stamp_s: float


def default_output(path: Path) -> Path:
    """``run.mcap.part`` -> ``run.mcap``; ``run.mcap`` -> ``run.recovered.mcap``."""
    if path.name.endswith(".part"):
        return path.with_name(path.name[: -len(".part")])
    return path.with_name(f"{path.stem}.recovered{path.suffix or '.mcap'}")


def recover_recording(path: str | Path, out_path: str | Path | None = None) -> RecoveryResult:
    """Copy every complete record of ``path`` into a proper MCAP file at ``out_path``.

    Raises FileNotFoundError / ValueError (naming the file) when ``path`` is missing, is not
    an MCAP file at all or is cut off before anything could be recovered (nothing is written
    then); the output is written as ``<out>.recovering`` and renamed when complete.
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
    n_msg = n_att = 0
    last_ns = None
    complete = True
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    with open(path, "rb") as src, open(part, "wb") as dst:
        writer = Writer(dst, compression=CompressionType.ZSTD)
        profile, library = "", "dm2 recover"
        records = StreamReader(src, validate_crcs=True).records
        started = False
        try:
            for rec in records:
                if not started:
                    profile = getattr(rec, "profile", "")
                    writer.start(profile=profile, library=library)
                    started = True
                    continue
                if isinstance(rec, Schema):
                    if rec.id not in schema_ids:
                        schema_ids[rec.id] = writer.register_schema(rec.name, rec.encoding,
                                                                    rec.data)
                elif isinstance(rec, Channel):
                    if rec.id not in channel_ids:
                        channel_ids[rec.id] = writer.register_channel(
                            rec.topic, rec.message_encoding, schema_ids.get(rec.schema_id, 0),
                            rec.metadata)
                elif isinstance(rec, Message):
                    cid = channel_ids.get(rec.channel_id)
                    if cid is None:
                        continue
                    writer.add_message(cid, log_time=rec.log_time, data=rec.data,
                                       publish_time=rec.publish_time, sequence=rec.sequence)
                    n_msg += 1
                    last_ns = rec.log_time if last_ns is None else max(last_ns, rec.log_time)
                elif isinstance(rec, Attachment):
                    writer.add_attachment(create_time=rec.create_time, log_time=rec.log_time,
                                          name=rec.name, media_type=rec.media_type,
                                          data=rec.data)
                    n_att += 1
                elif isinstance(rec, Metadata):
                    writer.add_metadata(rec.name, dict(rec.metadata))
            else:
                complete = True
        except (McapError, EOFError, ValueError, struct.error, KeyError) as exc:
            complete = False
            log.info("%s: stopped at a damaged or missing record (%s)", path,
                     str(exc) or type(exc).__name__)
        if not started:
            writer.start(profile=profile, library=library)
        writer.finish()
    if not complete and n_msg == 0 and n_att == 0:
        part.unlink()
        raise ValueError(f"{path}: nothing to recover: the file is cut off before its first "
                         f"complete message or attachment")
    part.replace(out)
    stamp = last_ns / 1e9 if last_ns is not None else float("nan")
    log.info("recovered %s -> %s: %d messages, %d attachments%s", path, out, n_msg, n_att,
             "" if complete else " (input was cut off)")
    return RecoveryResult(out, n_msg, n_att, complete, stamp)
