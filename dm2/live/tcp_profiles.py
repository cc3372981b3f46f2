"""The listening source of the TCP profile protocol (:mod:`dm2.live.tcp_frames`) and a client.

:class:`ProfileServer` accepts sensor-side bridges (loopback by default; connections from hosts
other than the configured bridges count ``foreign_sender``), parses each connection's frame
stream and feeds the profiles to the live inbox with the parser's drop counts.
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


class ProfileServer:
    """TCP listener for profile bridges, feeding an :class:`Inbox` (source ``"profiles"``).

    Parameters
    ----------
    inbox : destination of the decoded profiles and of the drop counts
    host, port : address to listen on (loopback by default)
    bridges : peer IP addresses accepted; other connections are closed (``foreign_sender``)
    max_frame_bytes : larger frames count ``oversized_frame``
    max_connections : concurrent bridge connections at most
    """

    name = "profiles"

    def __init__(self, inbox: Inbox, host: str = "127.0.0.1", port: int = DEFAULT_PROFILE_PORT,
                 bridges=("127.0.0.1",), max_frame_bytes: int = MAX_FRAME_BYTES,
                 max_connections: int = 8):
        self.inbox = inbox
        self.bridges = frozenset(bridges)
        self.max_frame_bytes = int(max_frame_bytes)
        self.max_connections = int(max_connections)
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
        self._conns: set[socket.socket] = set()
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
                if len(self._conns) >= self.max_connections:
                    self.inbox.drop("connection_limit")
                    conn.close()
                    continue
                self._conns.add(conn)
                self.connections += 1
            t = threading.Thread(target=self._serve, args=(conn, addr), daemon=True,
                                 name=f"profile-bridge-{addr[1]}")
            self._threads.append(t)
            t.start()

    def _serve(self, conn: socket.socket, addr) -> None:
        parser = FrameParser(self.max_frame_bytes)
        conn.settimeout(0.1)
        log.info("profile bridge connected from %s:%d", *addr)
        try:
            while not self._stop.is_set():
                try:
                    data = conn.recv(65536)
                except TimeoutError:
                    continue
                except OSError:
                    break
                if not data:
                    break
                arrival = time.monotonic()
                for p in parser.feed(data):
                    self.inbox.put(p, self.name, arrival)
        finally:
            parser.close()
            for reason, n in parser.dropped.items():
                self.inbox.drop(reason, n)
            with self._lock:
                self._conns.discard(conn)
                self.disconnects += 1
            conn.close()
            log.info("profile bridge %s:%d disconnected", *addr)

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
        """Send raw bytes, reconnecting once if the connection dropped."""
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
