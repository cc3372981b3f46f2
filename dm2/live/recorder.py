"""Crash-safe live recording: MCAP chunks closed and pushed to the OS at least every second.

:class:`LiveRecorder` is a :class:`~dm2.recording.RecordingWriter` that, besides closing a
chunk after ``chunk_s`` of message time, also closes it after ``chunk_s`` of wall time and
flushes Python's file buffer each time, so a process killed with SIGKILL leaves every chunk
but the one in progress on disk (at most about ``chunk_s`` of messages lost). The file stays
``<path>.part`` until :meth:`close`; :func:`dm2.live.recover.recover_recording` turns a
``.part`` left behind by a crash into a complete, indexed recording.
"""

from __future__ import annotations

import time

from dm2.recording import RecordingWriter


class LiveRecorder(RecordingWriter):
    """RecordingWriter with a wall-clock bound on the unflushed data.

    Parameters
    ----------
    path : output file (written as ``<path>.part``, renamed on close)
    attachments : name -> bytes
    chunk_s : float [s], message-time and wall-time bound of one chunk
    """

    def __init__(self, path, *, attachments=None, chunk_s: float = 1.0):
        super().__init__(path, attachments=attachments, chunk_s=chunk_s)
        self._chunk_wall_s = float(chunk_s)
        self._file.flush()  # header, schemas and attachments are on disk from the start
        self._last_flush = time.monotonic()

    def _add(self, topic, schema, stamp_ns, data, sequence=0):
        chunk_before = self._chunk_start_ns
        super()._add(topic, schema, stamp_ns, data, sequence)
        now = time.monotonic()
        if self._chunk_start_ns != chunk_before and chunk_before is not None:
            self._file.flush()  # the message-time bound closed a chunk
            self._last_flush = now
        elif now - self._last_flush >= self._chunk_wall_s:
            self.flush()

    def flush(self) -> None:
        """Close the chunk in progress and push everything written so far to the OS."""
        if self._closed:
            return
        self._mcap.flush()
        self._file.flush()
        self._chunk_start_ns = None
        self._last_flush = time.monotonic()
