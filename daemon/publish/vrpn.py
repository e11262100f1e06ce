"""VRPN tracker server: one tracker per rigid body, named by the body, for VRPN clients.

Why our own wire code instead of the VRPN library: the protocol a tracker server speaks is
small and stable (VRPN 07.xx), and a pure-Python server needs no C++ build on the robot
computer. What it speaks, as vrpn_Connection.C lays it out (network byte order):

- connection: the server listens on TCP and UDP port 3883. A client normally lobs a UDP
  datagram "ADDRESS PORT\\0" and waits for the server to connect back to that TCP port
  (VRPN's default); `tcp://host:port` clients connect directly. Both sides then send a
  24-byte cookie, "vrpn: ver. 07.35  0" (the last digit is the remote log mode).
- messages: a 24-byte header (five int32: length = 24 + payload length, time seconds and
  microseconds, sender id, type id; then a sequence number as padding), then the payload
  padded to 8 bytes. Negative types are system messages: -1 describes a sender (its id is
  the header's sender field, the payload an int32 length and the name), -2 a type, -3 the
  client's UDP port for low-latency messages (port in the sender field, address as text).
- after the cookies the server describes its senders (one per rigid body, by name) and its
  types ("vrpn_Tracker Pos_Quat", "vrpn_Base pong_message"). Each frame, every tracked body
  gets a Pos_Quat message (int32 sensor 0, int32 padding, position as three doubles,
  quaternion x y z w as four doubles), sent over the client's UDP port when it gave one
  (as VRPN sends its low-latency class), else over TCP. A body that is not tracked is not
  sent: VRPN clients (libmotioncapture) then report it missing, not at a stale pose.
- clients ping each tracker once a second ("vrpn_Base ping_message", no payload); the
  server answers with a pong from the same sender, or the client warns that the server
  is not responding.

A client that stops reading has its output buffered up to `max_backlog_bytes` and is then
dropped; others are not held up (sockets are non-blocking; one server thread accepts,
reads and flushes, the publisher thread packs frames).
"""

from __future__ import annotations

import logging
import os
import select
import socket
import struct
import threading
import time

import numpy as np

from daemon.process.supervise import Supervised
from daemon.publish.base import Publisher

# the wire format (daemon/publish/vrpn_wire.py); POS_QUAT too, so that `vrpn.X` names it all
from daemon.publish.vrpn_wire import (
    COOKIE_SIZE,
    MAGIC_MAJOR,
    OUR_TYPES,
    PING,
    PONG,
    POS_QUAT,  # noqa: F401
    POSE_MESSAGE,
    SENDER_DESCRIPTION,
    TYPE_DESCRIPTION,
    UDP_DESCRIPTION,
    UDP_MAX,
    _lob_port,
    check_cookie,
    cookie,
    describe,
    pack,
    pose_messages,
    unpack_messages,
)

log = logging.getLogger("mocapd.publish")


class _Client:
    """One connected VRPN client (a vrpn_Endpoint on the other side)."""

    def __init__(self, sock: socket.socket, peer) -> None:
        self.sock = sock
        self.peer = peer
        self.inbuf = bytearray()
        self.outbuf = bytearray()
        self.connected = False  # cookies exchanged, descriptions sent
        self.senders: dict[int, str] = {}  # the client's ids -> names
        self.types: dict[int, str] = {}
        self.udp: tuple[str, int] | None = None
        self.lock = threading.Lock()
        self.seq = 0
        self.pings = 0

    def write(self, data: bytes, limit: int) -> None:
        """Queue and try to send now; raise OSError when the client has too much unread."""
        with self.lock:
            self.outbuf += data
            self._flush()
            if len(self.outbuf) > limit:
                raise OSError(f"client {self.peer[0]}:{self.peer[1]} is not reading "
                              f"({len(self.outbuf)} bytes waiting)")

    def flush(self) -> None:
        with self.lock:
            self._flush()

    def _flush(self) -> None:
        while self.outbuf:
            try:
                n = self.sock.send(self.outbuf)
            except BlockingIOError:
                return
            del self.outbuf[:n]


class VrpnPublisher(Publisher):
    """A VRPN server with one tracker per rigid body."""

    takes_over = True  # its command port (and clients) pass from the server it replaces

    # open servers by (host, port): a reload's new server takes over the old one's sockets
    # and connected clients (daemon.capture.pipeline starts it before stopping the old one), so
    # clients stay connected instead of reconnecting seconds later
    _live: dict[tuple, VrpnPublisher] = {}
    _live_lock = threading.Lock()

    def __init__(self, bodies=(), host: str = "127.0.0.1", port: int = 3883,
                 rate_hz: float = 0.0, udp: bool = True, max_backlog_bytes: int = 1 << 20,
                 name: str = "vrpn") -> None:
        # if the port is taken (another program, another process), retry soon
        super().__init__(rate_hz=rate_hz, retry_s=0.1)
        self.bodies = list(bodies)
        self.host, self.port = host, port
        self.use_udp = udp
        self.max_backlog = max_backlog_bytes
        self.name = name
        self.body_names = [b.name for b in self.bodies]
        self._sender_of = {int(b.id): i for i, b in enumerate(self.bodies)}
        self.listen_sock: socket.socket | None = None
        self.udp_sock: socket.socket | None = None
        self.clients: list[_Client] = []
        self.handed_over = False
        self.pongs = 0
        self._lock = threading.Lock()
        self._srv_thread: Supervised | None = None
        self._srv_stop = threading.Event()
        self._calling: dict[socket.socket, tuple] = {}  # call backs under way
        self._bad_logged: dict[str, float] = {}  # kind of bad input -> when last logged
        self._senders_ids: tuple | None = None
        self._senders = np.zeros(0, np.int64)
        self._wall_offset_ns = time.time_ns() - time.monotonic_ns()

    # ---- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        try:
            self.open()
            self.connected = True
        except OSError as exc:
            self._failed(f"cannot open: {exc}")
        super().start()

    def open(self) -> None:
        if self.handed_over:
            raise OSError("handed over to the server that replaced this one")
        with VrpnPublisher._live_lock:
            old = VrpnPublisher._live.get((self.host, self.port)) if self.port else None
            taken = old._hand_over() if old is not None and old is not self else None
            if taken is not None:
                tcp, udp, clients = taken
            else:
                tcp, udp, clients = self._bind(), None, []
                udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                try:
                    udp.bind((self.host, tcp.getsockname()[1]))
                except OSError:
                    tcp.close()
                    udp.close()
                    raise
            self.port = tcp.getsockname()[1]
            VrpnPublisher._live[(self.host, self.port)] = self
        tcp.setblocking(False)
        udp.setblocking(False)
        self.listen_sock, self.udp_sock = tcp, udp
        with self._lock:
            self.clients = clients
        for c in clients:  # taken over: tell them our trackers (names may have changed)
            if c.connected:
                try:
                    c.write(self._hello(), self.max_backlog)
                except OSError:
                    self._drop(c)
        self._wall_offset_ns = time.time_ns() - time.monotonic_ns()
        self._srv_stop.clear()
        self._srv_thread = Supervised(f"{self.name}-srv", self._serve,
                                      stopping=self._srv_stop.is_set).start()
        log.info("%s: VRPN trackers %s on %s:%d%s", self.name,
                 ", ".join(self.body_names) or "-", self.host, self.port,
                 f" (taken over with {len(clients)} clients)" if taken is not None else "")

    def _bind(self) -> socket.socket:
        tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            tcp.bind((self.host, self.port))
            tcp.listen(8)
        except OSError:
            tcp.close()
            raise
        return tcp

    def _hand_over(self):
        """Give the sockets and the connected clients to the server replacing this one (a
        reload), which keeps them connected; this one stops and never opens again."""
        self.handed_over = True
        self._srv_stop.set()
        if self._srv_thread is not None:
            self._srv_thread.join(1.0)
            self._srv_thread = None
        with self._lock:
            tcp, udp, clients = self.listen_sock, self.udp_sock, self.clients
            self.listen_sock = self.udp_sock = None
            self.clients = []
        for sock in self._calling:
            sock.close()
        self._calling.clear()
        if tcp is None or udp is None:
            return None
        return tcp, udp, clients

    def _hello(self) -> bytes:
        """Our sender (one per body) and type descriptions."""
        return (b"".join(describe(SENDER_DESCRIPTION, i, n)
                         for i, n in enumerate(self.body_names))
                + b"".join(describe(TYPE_DESCRIPTION, i, n) for i, n in enumerate(OUR_TYPES)))

    def close(self) -> None:
        self._srv_stop.set()
        if self._srv_thread is not None:
            self._srv_thread.join(1.0)
            self._srv_thread = None
        with VrpnPublisher._live_lock:
            if VrpnPublisher._live.get((self.host, self.port)) is self:
                del VrpnPublisher._live[(self.host, self.port)]
        with self._lock:
            clients, self.clients = self.clients, []
            socks = (self.listen_sock, self.udp_sock)
            self.listen_sock = self.udp_sock = None
        for c in clients:
            c.sock.close()
        for sock in self._calling:
            sock.close()
        self._calling.clear()
        for s in socks:
            if s is not None:
                s.close()

    def status(self) -> dict:
        st = super().status()
        with self._lock:
            st["clients"] = sum(c.connected for c in self.clients)
        st["address"] = f"{self.host}:{self.port}"
        st["server_alive"] = self._srv_thread is not None and self._srv_thread.is_alive()
        st["server_restarts"] = self._srv_thread.restarts if self._srv_thread else 0
        return st

    @property
    def supervised(self) -> list:
        return [*super().supervised, self._srv_thread]

    # ---- frames ------------------------------------------------------------------------------

    def send(self, result) -> None:
        ids = tuple(int(i) for i in result.poses.ids)
        if ids != self._senders_ids:
            self._senders_ids = ids
            self._senders = np.array([self._sender_of.get(i, -1) for i in ids], np.int64)
        t_s = (int(result.t_ns) + self._wall_offset_ns) * 1e-9
        msgs = pose_messages(result, self._senders, t_s)
        if not len(msgs):
            return
        with self._lock:
            clients = [c for c in self.clients if c.connected]
            udp = self.udp_sock
        per_datagram = max(1, UDP_MAX // POSE_MESSAGE.itemsize)
        for c in clients:
            msgs["seq"] = np.arange(c.seq, c.seq + len(msgs))
            c.seq += len(msgs)
            try:
                if c.udp is not None and self.use_udp and udp is not None:
                    for k in range(0, len(msgs), per_datagram):
                        udp.sendto(msgs[k:k + per_datagram].tobytes(), c.udp)
                else:
                    c.write(msgs.tobytes(), self.max_backlog)
            except OSError as exc:
                log.warning("%s: dropping %s:%d: %s", self.name, *c.peer[:2], exc)
                self._drop(c)

    # ---- the server thread: accept, connect back, read, flush ------------------------------

    def _bad_input(self, what: str) -> None:
        """One log line per kind of bad input and minute: a flood of junk must not flood
        the log too."""
        now = time.monotonic()
        if now - self._bad_logged.get(what.split(" ", 1)[0], -1e9) >= 60.0:
            self._bad_logged[what.split(" ", 1)[0]] = now
            log.info("%s: ignoring %s", self.name, what)

    def _serve(self) -> None:
        """The server's loop; a step that raises (a bug) restarts it (daemon.process.supervise), so
        one bad client cannot stop every client's stream."""
        while not self._srv_stop.is_set():
            self._serve_once()

    def _serve_once(self) -> None:
        """One pass: wait up to 50 ms, then accept, call back, read and flush."""
        with self._lock:
            clients = list(self.clients)
        reads = [self.listen_sock, self.udp_sock] + [c.sock for c in clients]
        writes = [c.sock for c in clients if c.outbuf] + list(self._calling)
        try:
            r, w, _ = select.select(reads, writes, [], 0.05)
        except (OSError, ValueError):  # a socket closed under us: look again
            return
        if self.listen_sock in r:
            self._accept()
        if self.udp_sock in r:
            self._lob()
        for sock in list(self._calling):
            self._called(sock, sock in w)
        for c in clients:
            try:
                if c.sock in w:
                    c.flush()
                if c.sock in r:
                    self._read(c)
            except (OSError, ValueError, struct.error) as exc:
                if not isinstance(exc, ConnectionError):
                    self._bad_input(f"client {c.peer[0]}:{c.peer[1]}: {exc}")
                self._drop(c)

    def _accept(self) -> None:
        try:
            sock, peer = self.listen_sock.accept()
        except OSError:
            return
        self._new_client(sock, peer)

    def _lob(self) -> None:
        """A client's UDP request: connect back to the TCP port it names, on the address
        the datagram came from (never to another host it names: a forged datagram must not
        turn the server into a port scanner)."""
        try:
            data, src = self.udp_sock.recvfrom(1024)
        except OSError:
            return
        port = _lob_port(data)
        if port is None:
            self._bad_input(f"a UDP datagram from {src[0]}:{src[1]} that is not "
                            f"'ADDRESS PORT'")
            return
        target = (src[0], port)
        with self._lock:
            if any(c.peer == target for c in self.clients) or any(
                    t == target for t, _ in self._calling.values()):
                return  # already connected (the client lobs again every 2 s until it hears)
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setblocking(False)  # connect in the background: others are not held up
        try:
            sock.connect(target)
        except BlockingIOError:
            pass
        except OSError as exc:
            sock.close()
            log.info("%s: cannot call back %s:%d: %s", self.name, *target, exc)
            return
        self._calling[sock] = (target, time.monotonic() + 2.0)

    def _called(self, sock: socket.socket, writable: bool) -> None:
        """A call back finished connecting, failed, or took too long."""
        target, deadline = self._calling[sock]
        err = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) if writable else 0
        if writable and not err:
            del self._calling[sock]
            self._new_client(sock, target)
        elif err or time.monotonic() > deadline:
            del self._calling[sock]
            sock.close()
            log.info("%s: cannot call back %s:%d: %s", self.name, *target,
                     os.strerror(err) if err else "timed out")

    def _new_client(self, sock: socket.socket, peer) -> None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        c = _Client(sock, peer)
        with self._lock:
            self.clients.append(c)
        try:
            c.write(cookie(), self.max_backlog)
        except OSError:
            self._drop(c)
            return
        log.info("%s: client %s:%d connected", self.name, *peer[:2])

    def _drop(self, c: _Client) -> None:
        with self._lock:
            if c not in self.clients:
                return
            self.clients.remove(c)
        try:
            c.sock.close()
        except OSError:
            pass
        log.info("%s: client %s:%d left", self.name, *c.peer[:2])

    def _read(self, c: _Client) -> None:
        data = c.sock.recv(65536)
        if not data:
            raise ConnectionResetError("closed")
        c.inbuf += data
        if not c.connected:
            if len(c.inbuf) < COOKIE_SIZE:
                return
            if not check_cookie(bytes(c.inbuf[:COOKIE_SIZE])):
                raise ValueError(f"not a VRPN {MAGIC_MAJOR.decode()}xx client "
                                 f"(cookie {bytes(c.inbuf[:16])!r})")
            del c.inbuf[:COOKIE_SIZE]
            c.write(self._hello(), self.max_backlog)
            c.connected = True
        for sender, type_id, payload, _t in unpack_messages(c.inbuf):
            self._message(c, sender, type_id, payload)

    def _message(self, c: _Client, sender: int, type_id: int, payload: bytes) -> None:
        if type_id in (SENDER_DESCRIPTION, TYPE_DESCRIPTION):
            n = struct.unpack_from(">i", payload)[0]
            name = payload[4:4 + n].split(b"\0", 1)[0].decode("utf-8", "replace")
            (c.senders if type_id == SENDER_DESCRIPTION else c.types)[sender] = name
        elif type_id == UDP_DESCRIPTION:
            if not 0 < sender < 65536:
                raise ValueError(f"UDP description with port {sender}")
            c.udp = (c.peer[0], sender)  # the client's own address, whatever it names
        elif type_id >= 0 and c.types.get(type_id) == PING:
            name = c.senders.get(sender)
            if name in self.body_names:
                c.pings += 1
                c.write(pack(self.body_names.index(name), OUR_TYPES.index(PONG)),
                        self.max_backlog)
                self.pongs += 1
