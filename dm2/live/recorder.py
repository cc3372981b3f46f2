"""Crash-safe live recording: MCAP chunks closed and pushed to the OS at least every second.

:class:`LiveRecorder` is a :class:`~dm2.io.recording_writer.RecordingWriter` that, besides closing a
chunk after ``chunk_s`` of message time, also closes it after ``chunk_s`` of wall time and
flushes Python's file buffer each time, so a process killed with SIGKILL leaves every chunk
but the one in progress on disk (at most about ``chunk_s`` of messages lost). The file stays
``<path>.part`` until :meth:`close`; :func:`dm2.live.recover.recover_recording` turns a
``.part`` left behind by a crash into a complete, indexed recording.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections import deque

from dm2.core.messages import MessageError, RobotState
from dm2.io.recording import stamp_to_ns
from dm2.io.recording_writer import RecordingWriter

log = logging.getLogger(__name__)

MAX_STAMP_NS = (1 << 31) * 1_000_000_000  # ROS Time holds int32 seconds
YIELD_EVERY_S = 0.0005  # [s] the recorder thread offers the interpreter lock this often


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

    def flush_if_due(self) -> None:
        """Close the chunk in progress when it has been open for ``chunk_s`` of wall time
        (so a quiet stream still reaches the disk within the bound)."""
        if self._chunk_start_ns is not None and \
                time.monotonic() - self._last_flush >= self._chunk_wall_s:
            self.flush()

    def flush(self) -> None:
        """Close the chunk in progress and push everything written so far to the OS."""
        if self._closed:
            return
        self._mcap.flush()
        self._file.flush()
        self._chunk_start_ns = None
        self._last_flush = time.monotonic()


class RecorderThread:
    """A :class:`LiveRecorder` fed from a bounded queue by a background thread.

    Encoding and writing the recording (ROS 2 CDR, MCAP chunks) then happens off the live
    loop's hot path, in the time the loop waits for the next message; while writing a backlog
    the thread offers the interpreter lock every ``YIELD_EVERY_S``, so the loop never waits a
    whole switch interval (5 ms) for it behind the recorder. :meth:`write` checks
    what would make a message unrecordable (a negative stamp, a sequence number beyond 32
    bits) at once, so the caller still learns of it, and queues the message; the thread wakes
    at least every ``max_wait_s`` and writes everything queued, so a SIGKILL loses at most the
    recorder's ``chunk_s`` plus ``max_wait_s`` of messages. A full queue drops the message and
    counts it in :attr:`dropped` (``recording_queue_full``) rather than blocking the loop; a
    message the writer still cannot encode is skipped and counted (``unrecordable_message``)
    and recording goes on: only a failing file stops it.

    Parameters
    ----------
    recorder : the LiveRecorder written to (owned by this object from now on)
    maxsize : int, messages queued at most
    max_wait_s : float [s], longest a queued message waits before it is written
    """

    def __init__(self, recorder: LiveRecorder, maxsize: int = 50000, max_wait_s: float = 0.05):
        if maxsize <= 0:
            raise ValueError(f"RecorderThread: maxsize must be positive, got {maxsize}")
        self.recorder = recorder
        self.maxsize = int(maxsize)
        self.max_wait_s = float(max_wait_s)
        self.dropped: dict[str, int] = {}
        self.written = 0
        self._queue: deque = deque()
        self._wake = threading.Condition()
        self._stop = False
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._loop, name="live-recorder", daemon=True)
        self._thread.start()

    @property
    def path(self):
        return self.recorder.path

    def write(self, msg) -> None:
        """Queue one pipeline message; MessageError at once when it cannot be recorded."""
        ns = stamp_to_ns(msg.stamp_s)
        if ns >= MAX_STAMP_NS:
            raise MessageError(f"stamp_s: {msg.stamp_s!r} s does not fit a ROS Time stamp")
        if isinstance(msg, RobotState) and not 0 <= msg.seq < 1 << 32:
            raise MessageError(f"RobotState.seq: {msg.seq} does not fit 32 bits unsigned")
        if len(self._queue) >= self.maxsize:
            self.dropped["recording_queue_full"] = self.dropped.get("recording_queue_full",
                                                                    0) + 1
            return
        self._queue.append(msg)  # deque appends are atomic: no lock on the hot path

    def _loop(self) -> None:
        q, rec = self._queue, self.recorder
        while True:
            with self._wake:
                if not self._stop:
                    self._wake.wait(self.max_wait_s)
                stop = self._stop
            try:
                slice_end = time.perf_counter() + YIELD_EVERY_S
                while q:
                    msg = q.popleft()
                    try:
                        rec.write(msg)
                        self.written += 1
                    except (MessageError, ValueError, OverflowError, struct.error) as exc:
                        # one message that cannot be encoded costs that message only
                        self.dropped["unrecordable_message"] = \
                            self.dropped.get("unrecordable_message", 0) + 1
                        log.warning("recording: skipped a message: %s", exc)
                    if time.perf_counter() >= slice_end:
                        time.sleep(0)  # hand the interpreter lock to a waiting thread
                        slice_end = time.perf_counter() + YIELD_EVERY_S
                rec.flush_if_due()
            except BaseException as exc:  # noqa: BLE001 - reported by close()
                self._error = exc
                log.exception("the live recording failed; recording stops here")
                return
            if stop:
                return

    def close(self, keep_part: bool = False):
        """Write what is queued, stop the thread and close the recording."""
        with self._wake:
            self._stop = True
            self._wake.notify()
        self._thread.join()
        path = self.recorder.close(keep_part=keep_part or self._error is not None)
        if self._error is not None:
            raise OSError(f"{self.recorder.path}: recording failed: {self._error}")
        return path
