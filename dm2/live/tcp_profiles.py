"""The listening source of the TCP profile protocol (:mod:`dm2.live.tcp_frames`) and a client.

:class:`ProfileServer` accepts sensor-side bridges (loopback by default; connections from hosts
other than the configured bridges count ``foreign_sender``), parses each connection's frame
stream and feeds the profiles to the live inbox; the parser's drop counts reach the inbox as
they happen, not only when the connection closes. The port stays available: a connection that
sent no valid frame for ``idle_timeout_s`` is closed (``idle_connection``), and when all
``max_connections`` are taken a new bridge replaces the connection idle the longest (one
without a valid frame for at least ``EVICT_IDLE_S``; ``idle_connection`` too); only when every
connection is busy is the newcomer refused (``connection_limit``).
:class:`ProfileClient` is the sending side (the twin's rehearsal, bridges written in Python);
it reconnects after a dropped connection.
"""

from __future__ import annotations

import logging
import socket
import threading
import time

from dm2.core.messages import Profile
from dm2.live.inbox import Inbox
from dm2.live.tcp_frames import MAX_FRAME_BYTES, FrameParser, encode_frame

log = logging.getLogger(__name__)

DEFAULT_PROFILE_PORT = 6511
EVICT_IDLE_S = 1.0  # [s] a connection this long without a valid frame yields to a newcomer


class ProfileServer:
    """TCP listener for profile bridges, feeding an :class:`Inbox` (source
    ``"profiles HOST:PORT"``, one per connection).

    Parameters
    ----------
    inbox : destination of the decoded profiles and of the drop counts
    host, port : address to listen on (loopback by default)
    bridges : peer IP addresses accepted; other connections are closed (``foreign_sender``)
    max_frame_bytes : larger frames count ``oversized_frame``
    max_connections : concurrent bridge connections at most
    idle_timeout_s : a connection without a valid frame this long is closed (0: never)
    """

    name = "profiles"

    def __init__(self, inbox: Inbox, host: str = "127.0.0.1", port: int = DEFAULT_PROFILE_PORT,
                 bridges=("127.0.0.1",), max_frame_bytes: int = MAX_FRAME_BYTES,
                 max_connections: int = 8, idle_timeout_s: float = 10.0):
        self.inbox = inbox
        self.idle_timeout_s = float(idle_timeout_s)
        self.bridges = frozenset(bridges)
        self.max_frame_bytes = int(max_frame_bytes)
        self.max_connections = int(max_connections)
        self.on_close: list = []  # callables f(source) told when a connection has closed
        self.connections = 0  # accepted so far
        self.disconnects = 0
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind((host, int(port)))
        self._sock.listen(self.max_connections)
        self._sock.settimeout(0.1)
        self.address = self._sock.getsockname()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._conns: dict[socket.socket, float] = {}  # -> last valid frame (or accept) [s]
        self._lock = threading.Lock()

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, addr = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            if addr[0] not in self.bridges:
                self.inbox.drop("foreign_sender")
                conn.close()
                continue
            with self._lock:
                if len(self._conns) >= self.max_connections and not self._evict_idlest():
                    self.inbox.drop("connection_limit")
                    conn.close()
                    continue
                self._conns[conn] = time.monotonic()
                self.connections += 1
            t = threading.Thread(target=self._serve, args=(conn, addr), daemon=True,
                                 name=f"profile-bridge-{addr[1]}")
            self._threads.append(t)
            t.start()

    def _evict_idlest(self) -> bool:
        """Shut the connection idle the longest if it is idle enough (lock held); the
        connection's thread then closes it. True when one was shut."""
        now = time.monotonic()
        conn, last = min(self._conns.items(), key=lambda kv: kv[1], default=(None, now))
        if conn is None or now - last < EVICT_IDLE_S:
            return False
        self._conns.pop(conn)  # its thread sees it gone and closes it
        self.inbox.drop("idle_connection")
        try:
            conn.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        log.info("profile connection idle for %.1f s replaced by a new bridge", now - last)
        return True

    def _serve(self, conn: socket.socket, addr) -> None:
        parser = FrameParser(self.max_frame_bytes)
        conn.settimeout(0.1)
        reported: dict[str, int] = {}
        source = f"{self.name} {addr[0]}:{addr[1]}"  # one stream per connection
        log.info("profile bridge connected from %s:%d", *addr)
        try:
            while not self._stop.is_set():
                try:
                    data = conn.recv(65536)
                except TimeoutError:
                    data = None
                except OSError:
                    break
                now = time.monotonic()
                if data is not None:
                    if not data:
                        break
                    n = 0
                    for p in parser.feed(data):
                        self.inbox.put(p, source, now)
                        n += 1
                    if n:
                        with self._lock:
                            if conn in self._conns:
                                self._conns[conn] = now
                    self._report(parser, reported)
                with self._lock:
                    last = self._conns.get(conn)
                if last is None:
                    break  # replaced by a newer bridge
                if self.idle_timeout_s and now - last > self.idle_timeout_s:
                    self.inbox.drop("idle_connection")
                    log.info("profile bridge %s:%d sent no valid frame for %.1f s: closed",
                             *addr, now - last)
                    break
        finally:
            parser.close()
            self._report(parser, reported)
            with self._lock:
                self._conns.pop(conn, None)
                self.disconnects += 1
            conn.close()
            for f in self.on_close:
                f(source)
            log.info("profile bridge %s:%d disconnected", *addr)

    def _report(self, parser: FrameParser, reported: dict) -> None:
        """Hand the parser's new drop counts to the inbox (while the connection is open)."""
        for reason, n in parser.dropped.items():
            new = n - reported.get(reason, 0)
            if new:
                self.inbox.drop(reason, new)
                reported[reason] = n

    def start(self) -> ProfileServer:
        t = threading.Thread(target=self._accept_loop, name="profile-server", daemon=True)
        self._threads.append(t)
        t.start()
        log.info("profile server listening on tcp %s:%d", *self.address)
        return self

    def close(self) -> None:
        self._stop.set()
        for t in list(self._threads):
            t.join(timeout=2.0)
        self._sock.close()

    def __enter__(self) -> ProfileServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


class ProfileClient:
    """A bridge's side: connect to the monitor and send frames, reconnecting after a drop.

    Parameters
    ----------
    host, port : the monitor's profile server
    connect_timeout_s : how long :meth:`send` keeps retrying to (re)connect
    """

    def __init__(self, host: str, port: int, connect_timeout_s: float = 10.0):
        self.host, self.port = host, int(port)
        self.connect_timeout_s = float(connect_timeout_s)
        self.reconnects = 0
        self._sock: socket.socket | None = None
        self._last_send = 0.0

    def connect(self) -> None:
        """Connect now (no-op when connected), retrying for up to ``connect_timeout_s``;
        ConnectionError when the server does not accept in that time."""
        if self._sock is None:
            self._connect()

    def _connect(self) -> None:
        deadline = time.monotonic() + self.connect_timeout_s
        while True:
            try:
                self._sock = socket.create_connection((self.host, self.port), timeout=1.0)
                self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                return
            except OSError:
                if time.monotonic() > deadline:
                    raise ConnectionError(f"cannot connect to the profile server at "
                                          f"{self.host}:{self.port}") from None
                time.sleep(0.05)

    def send_bytes(self, data: bytes) -> None:
        """Send raw bytes, reconnecting once if the connection dropped (or, after a pause,
        if the server closed it meanwhile: an idle timeout must not cost the next frame)."""
        now = time.monotonic()
        if self._sock is not None and now - self._last_send > 1.0 and self._peer_closed():
            self.drop_connection()
        self._last_send = now
        for attempt in range(2):
            if self._sock is None:
                self._connect()
                if attempt:
                    self.reconnects += 1
            try:
                self._sock.sendall(data)
                return
            except OSError:
                self.drop_connection()
        raise ConnectionError(f"profile server {self.host}:{self.port} keeps dropping")

    def _peer_closed(self) -> bool:
        sock = self._sock
        try:
            sock.setblocking(False)
            return sock.recv(1, socket.MSG_PEEK) == b""
        except BlockingIOError:
            return False
        except OSError:
            return True
        finally:
            try:
                sock.settimeout(1.0)
            except OSError:
                pass

    def send(self, p: Profile) -> None:
        self.send_bytes(encode_frame(p))

    def drop_connection(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None

    def close(self) -> None:
        self.drop_connection()
