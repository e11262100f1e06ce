"""NatNet server: what OptiTrack's Motive streams and answers, so NatNet clients read mocapd.

Why 4.1 by default and others on request: clients written against 4.1 (libmotioncapture,
the `natnet` package, lab scripts built on NatNet SDK 4.1's PacketClient) cannot parse
4.2's rigid-body descriptions, while every newer client reads 4.1 and can ask for what it
wants ("Bitstream,4.2"). The server info announces 4.1, multicast carries 4.1; a unicast
client that asks gets its own version (3.0, 3.1, 4.1, 4.2 and later: natnet_wire.py).

The command port (UDP, default 1510): NAT_CONNECT and NAT_DISCOVERY get NAT_SERVERINFO
(application name, versions, the clock frequency of the tick stamps, the data port,
multicast or not, the group); NAT_REQUEST_MODELDEF gets NAT_MODELDEF in the sender's
version; NAT_ECHOREQUEST gets NAT_ECHORESPONSE (its stamp back and our clock in the middle
of the request's stay with us, from the kernel's arrival stamp: arrival_stamps.py; what
NatNet clients' clock synchronisation, and so SecondsSinceHostTimestamp, rests on);
NAT_KEEPALIVE subscribes the sender to unicast frames for `keepalive_timeout_s`;
NAT_REQUEST_FRAMEOFDATA gets the latest frame; NAT_DISCONNECT (and the "Disconnect"
command) unsubscribes; NAT_REQUEST carries Motive's command strings
(natnet_commands.py: Bitstream, FrameRate, subscriptions, recording, ...).

Frames (NAT_FRAMEOFDATA) go to the multicast group on the data port (default
239.255.42.99:1511) and to every keep-alive subscriber, each in its version and with what
it subscribed to. With multicast off they also go to the data port of each connected
client's address, where libmotioncapture listens without sending keep-alives (dropped
when that port refuses them). Each carries the frame number, marker sets, rigid bodies,
labelled markers, the SMPTE timecode of the capture time (UTC time of day), the three
clock ticks (mid-exposure, data received, transmit; monotonic ns, frequency 1e9) and from
4.1 the precision timestamp (UTC seconds and nanoseconds of the capture).

Bodies that are not tracked are sent with the valid flag cleared and a zero pose: clients
(libmotioncapture, the NatNet SDK) then drop them rather than reuse a stale pose.

Axes: our world is z-up. `up_axis="y"` gives Motive's default y-up frame: x stays, y is our
z, z is our -y; body frames are rotated the same way, so a body at rest reads the identity
rotation in both conventions.

Sockets live on this publisher's own command thread (it answers clients even when no frame
comes) and worker thread (frames); a client that goes away only stops receiving.
"""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time

from daemon.process.supervise import Supervised
from daemon.publish.arrival_stamps import receive_stamped, residence_midpoint_ns, stamp_arrivals
from daemon.publish.base import Publisher
from daemon.publish.natnet_commands import Commands, code
from daemon.publish.natnet_wire import (
    DEFAULT_VERSION,
    EVERYTHING,
    MARKERSET_ID,
    MAX_PAYLOAD,
    NAT_CONNECT,
    NAT_DISCONNECT,
    NAT_DISCOVERY,
    NAT_ECHOREQUEST,
    NAT_ECHORESPONSE,
    NAT_FRAMEOFDATA,
    NAT_KEEPALIVE,
    NAT_MODELDEF,
    NAT_REQUEST,
    NAT_REQUEST_FRAMEOFDATA,
    NAT_REQUEST_MODELDEF,
    NAT_RESPONSE,
    NAT_SERVERINFO,
    NAT_UNRECOGNIZED_REQUEST,
    NATNET_VERSION,
    Y_UP,
    MarkerModel,
    View,
    axes,
    echo_response,
    frame_payload,
    message,
    model_definitions,
    precision_timestamp,
    server_info,
    timecode,
)

__all__ = ["NatNetPublisher", "MARKERSET_ID", "MAX_PAYLOAD", "NAT_CONNECT", "NAT_DISCONNECT",
           "NAT_DISCOVERY", "NAT_ECHOREQUEST", "NAT_ECHORESPONSE", "NAT_FRAMEOFDATA",
           "NAT_KEEPALIVE", "NAT_MODELDEF", "NAT_REQUEST", "NAT_REQUEST_FRAMEOFDATA",
           "NAT_REQUEST_MODELDEF", "NAT_RESPONSE", "NAT_SERVERINFO",
           "NAT_UNRECOGNIZED_REQUEST", "Y_UP", "MarkerModel", "frame_payload", "message",
           "model_definitions", "server_info"]

log = logging.getLogger("mocapd.publish")

DIRECT_GRACE_S = 3.0  # a keep-alive-less unicast client has this long to open its data port


class NatNetPublisher(Publisher):
    """Serves NatNet: answers the command port, sends frames by multicast and unicast."""

    takes_over = True  # its command port (and clients) pass from the server it replaces

    # open servers by (interface, command port). A reload starts the new publisher while
    # the old one still runs (daemon.capture.pipeline): the new one takes over the old one's command
    # socket and clients, so no request goes unanswered and no client has to connect again
    # (libmotioncapture never does)
    _live: dict[tuple, NatNetPublisher] = {}
    _live_lock = threading.Lock()

    def __init__(self, bodies=(), interface: str = "127.0.0.1", command_port: int = 1510,
                 data_port: int = 1511, multicast: bool = True,
                 group: str = "239.255.42.99", up_axis: str = "z", ttl: int = 1,
                 rate_hz: float = 0.0, legacy_unlabeled: bool = False,
                 keepalive_timeout_s: float = 10.0, name: str = "natnet",
                 marker_sets: bool = True, markerset=None,
                 markerset_id: int = MARKERSET_ID, fps: float = 240.0,
                 record_dir=None, control=None, record_from=("127.0.0.1",),
                 record_max_s: float = 3600.0, record_max_mb: float = 2000.0) -> None:
        """`markerset`: (name, marker names) of the live marker set, if one is configured;
        its labelled markers carry model id `markerset_id`. `fps`: the cameras' rate
        (FrameRate, the timecode's subframes); `record_dir` and `control` (the daemon's
        control handler): where and how StartRecording records; `record_from`,
        `record_max_s`, `record_max_mb`: who may record and for how long (Commands)."""
        # if the port is taken (another program; a server of another process), retry soon
        super().__init__(rate_hz=rate_hz, retry_s=0.1)
        axes(up_axis)
        self.bodies = list(bodies)
        self.interface, self.command_port, self.data_port = interface, command_port, data_port
        self.multicast, self.group, self.ttl = multicast, group, ttl
        self.up_axis = up_axis
        self.legacy_unlabeled = legacy_unlabeled
        self.keepalive_timeout_s = keepalive_timeout_s
        self.name = name
        self.cmd_sock: socket.socket | None = None
        self.data_sock: socket.socket | None = None
        self.subscribers: dict[tuple[str, int], float] = {}  # address -> last keep-alive
        self.direct: dict[str, tuple] = {}  # unicast: client IP -> (socket, since)
        self.direct_grace_s = DIRECT_GRACE_S
        self.requests = 0
        self.latest: bytes | None = None
        self.t0_ns: int | None = None
        self._lock = threading.Lock()
        self.handed_over = False
        self._cmd_thread: Supervised | None = None
        self._cmd_stop = threading.Event()
        self.markerset, self.markerset_id = markerset, markerset_id
        self.fps = float(fps)
        self.marker_sets = marker_sets
        self._modeldefs: dict[tuple[int, int], bytes] = {}
        self._marker_model = MarkerModel(self.bodies, markerset) if marker_sets else None
        self._info = server_info(data_port, multicast, group)
        self.commands = Commands(fps, self.bodies, record_dir, control, record_from,
                                 record_max_s, record_max_mb)
        self.bad = self.commands.bad  # refused requests by kind, logged once a minute each
        # the capture clock (monotonic) to UTC, for the timecode and precision timestamp
        self._wall_offset_ns = time.time_ns() - time.monotonic_ns()
        self.echoes = 0

    # ---- lifecycle: the command port is open from start, not from the first frame ---------

    def start(self) -> None:
        try:
            self.open()
            self.connected = True
        except OSError as exc:  # e.g. the port still held by the publisher a reload replaces
            self._failed(f"cannot open: {exc}")
        super().start()

    def open(self) -> None:
        if self.handed_over:
            raise OSError("handed over to the server that replaced this one")
        with NatNetPublisher._live_lock:
            old = NatNetPublisher._live.get((self.interface, self.command_port))
            taken = old._hand_over() if old is not None and old is not self else None
            if taken is not None:
                cmd, subscribers, direct_ips = taken
            else:
                cmd, subscribers, direct_ips = socket.socket(socket.AF_INET,
                                                             socket.SOCK_DGRAM), {}, []
                try:
                    cmd.bind((self.interface, self.command_port))
                except OSError:
                    cmd.close()
                    raise
            self.command_port = cmd.getsockname()[1]
            NatNetPublisher._live[(self.interface, self.command_port)] = self
        data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        data.setblocking(False)
        if self.multicast:
            data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, self.ttl)
            data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            if self.interface not in ("", "0.0.0.0"):
                data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF,
                                socket.inet_aton(self.interface))
        cmd.settimeout(0.2)
        stamp_arrivals(cmd)
        self.cmd_sock, self.data_sock = cmd, data
        with self._lock:
            self.subscribers.update(subscribers)
        if not self.multicast:
            for ip in direct_ips:
                self._direct(ip)
        self._cmd_stop.clear()
        self._cmd_thread = Supervised(f"{self.name}-cmd", self._serve,
                                      stopping=self._cmd_stop.is_set).start()
        log.info("%s: NatNet %d.%d on %s:%d, data %s%s:%d%s", self.name, *NATNET_VERSION[:2],
                 self.interface, self.command_port,
                 "multicast " if self.multicast else "unicast ",
                 self.group if self.multicast else "", self.data_port,
                 " (taken over)" if taken is not None else "")

    def _hand_over(self):
        """Give the command socket and the unicast clients to the server replacing this one;
        this one stops serving (its frames go nowhere) and never opens again."""
        self.handed_over = True
        self._cmd_stop.set()
        if self._cmd_thread is not None:
            self._cmd_thread.join(1.0)
            self._cmd_thread = None
        with self._lock:
            cmd, self.cmd_sock = self.cmd_sock, None
            subscribers, self.subscribers = self.subscribers, {}
            direct, self.direct = self.direct, {}
        for sock, _since in direct.values():
            sock.close()
        if cmd is None:
            return None
        return cmd, subscribers, list(direct)

    def close(self) -> None:
        self._cmd_stop.set()
        if self._cmd_thread is not None:
            self._cmd_thread.join(1.0)
            self._cmd_thread = None
        with NatNetPublisher._live_lock:
            if NatNetPublisher._live.get((self.interface, self.command_port)) is self:
                del NatNetPublisher._live[(self.interface, self.command_port)]
        with self._lock:
            direct, self.direct = [d[0] for d in self.direct.values()], {}
            cmd, self.cmd_sock = self.cmd_sock, None
        for s in (cmd, self.data_sock, *direct):
            if s is not None:
                s.close()
        self.data_sock = None

    @property
    def supervised(self) -> list:
        return [*super().supervised, self._cmd_thread]

    def status(self) -> dict:
        st = super().status()
        with self._lock:
            st["unicast_clients"] = len(self.subscribers) + len(self.direct)
        st["bad_requests"] = dict(self.bad.counts)
        # what is exposed: the command port's address (0.0.0.0: every interface)
        st["address"] = f"{self.interface}:{self.command_port}"
        return st

    # ---- frames ----------------------------------------------------------------------------

    def send(self, result) -> None:
        cmd = self.cmd_sock
        if cmd is None:  # handed over to the server that replaced this one
            return
        first = self.t0_ns is None
        if first:
            self.t0_ns = int(result.t_ns)
        wall_ns = int(result.t_ns) + self._wall_offset_ns
        common = dict(up_axis=self.up_axis, legacy_unlabeled=self.legacy_unlabeled,
                      t0_ns=self.t0_ns, models_changed=first,
                      marker_model=self._marker_model, markerset_id=self.markerset_id,
                      timecode=timecode(wall_ns, self.fps),
                      precision=precision_timestamp(wall_ns),
                      recording=self.commands.recording is not None)
        frames: dict[tuple, bytes] = {}

        def frame(version=DEFAULT_VERSION, view: View = EVERYTHING) -> bytes:
            """This frame in a version and view, encoded once for all who share them."""
            key = (version, view)
            if key not in frames:
                frames[key] = message(NAT_FRAMEOFDATA, frame_payload(
                    result, version=version, view=view, **common))
            return frames[key]

        data = frame()
        self.latest = data
        if self.multicast:
            try:
                self.data_sock.sendto(data, (self.group, self.data_port))
            except (BlockingIOError, ConnectionRefusedError):
                pass
            except OSError as exc:  # no route for the group (set `interface`): keep serving
                self._failed(f"multicast to {self.group}:{self.data_port}: "
                             f"{exc.strerror or exc}")
        now = time.monotonic()
        with self._lock:
            gone = [a for a, t in self.subscribers.items()
                    if now - t > self.keepalive_timeout_s]
            for a in gone:
                del self.subscribers[a]
                self.commands.forget(a)
            targets = list(self.subscribers)
            direct = list(self.direct.items())
        for addr in targets:
            try:
                cmd.sendto(frame(self.commands.version(addr), self.commands.view(addr)),
                           addr)
            except OSError:  # a client gone (ICMP refused): it expires with its keep-alives
                pass
        for ip, (sock, since) in direct:
            try:
                sock.send(data)
            except BlockingIOError:
                pass
            except OSError:  # refused: nobody listens there (yet: it binds after connecting)
                if now - since > self.direct_grace_s:
                    self._forget(ip)

    def model_definitions(self, version=DEFAULT_VERSION) -> bytes:
        """NAT_MODELDEF in a version, built once per version asked for."""
        if version not in self._modeldefs:
            self._modeldefs[version] = model_definitions(
                self.bodies, self.up_axis, self.marker_sets, self.markerset, version)
        return self._modeldefs[version]

    # ---- the command port ------------------------------------------------------------------

    def _serve(self) -> None:
        sock = self.cmd_sock
        while not self._cmd_stop.is_set():
            try:
                self.commands.check_budget()
            except Exception as exc:  # noqa: BLE001 - the budget must not end the server
                self.bad("failure stopping a take over its budget", exc)
            try:
                data, addr, arrived_ns = receive_stamped(sock)
            except TimeoutError:
                continue
            except OSError:
                if self._cmd_stop.is_set():
                    return
                continue
            try:
                reply = self.handle(data, addr, arrived_ns)
            except Exception as exc:  # noqa: BLE001 - a bad request must not end the server
                self.bad(f"request that failed ({type(exc).__name__})",
                         f"from {addr[0]}: {exc}")
                continue
            if reply:
                try:
                    sock.sendto(reply, addr)
                except OSError:
                    pass

    def handle(self, data: bytes, addr, arrived_ns: int | None = None) -> bytes | None:
        """The reply to one command-port datagram (None: no reply). `arrived_ns`: when the
        kernel received it (monotonic), if the socket stamps arrivals."""
        if len(data) < 4:
            self.bad("datagram shorter than a message header", f"from {addr[0]}")
            return None
        msg_id, size = struct.unpack_from("<HH", data)
        self.requests += 1
        if msg_id == NAT_ECHOREQUEST:
            self.echoes += 1
            return echo_response(data, residence_midpoint_ns(arrived_ns))
        if msg_id == NAT_CONNECT:  # a new session: no frames until its keep-alives
            with self._lock:
                self.subscribers.pop(addr, None)
                self.commands.forget(addr)
            if not self.multicast:
                self._direct(addr[0])
            return self._info
        if msg_id == NAT_DISCOVERY:  # a client looking for servers (by broadcast)
            return self._info
        if msg_id == NAT_KEEPALIVE:
            with self._lock:
                self.subscribers[addr] = time.monotonic()
            return None
        if msg_id == NAT_REQUEST_MODELDEF:
            return self.model_definitions(self.commands.version(addr))
        if msg_id == NAT_REQUEST_FRAMEOFDATA:
            return self.latest
        if msg_id == NAT_DISCONNECT:
            self._disconnect(addr)
            return None
        if msg_id == NAT_REQUEST:
            text = data[4:4 + size].split(b"\0", 1)[0].decode("utf-8", "replace")
            if text.strip().lower() == "disconnect":
                self._disconnect(addr)
                return code(0)
            with self._lock:
                unicast = (not self.multicast or addr in self.subscribers
                           or addr[0] in self.direct)
            reply = self.commands.answer(text, addr, unicast)
            return reply if reply is not None else message(NAT_UNRECOGNIZED_REQUEST, b"")
        self.bad("unknown message id", f"{msg_id} from {addr[0]}")
        return message(NAT_UNRECOGNIZED_REQUEST, b"")

    def _disconnect(self, addr) -> None:
        with self._lock:
            self.subscribers.pop(addr, None)
            self.commands.forget(addr)
        self._forget(addr[0])

    def _direct(self, ip: str) -> None:
        """Unicast without keep-alives, as libmotioncapture does it: after connecting it
        listens on the data port of its own address. A connected socket per client IP
        learns from the ICMP refusal when nobody listens there (any more)."""
        with self._lock:
            if ip in self.direct:
                self.direct[ip] = (self.direct[ip][0], time.monotonic())
                return
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        try:
            sock.connect((ip, self.data_port))
        except OSError:
            sock.close()
            return
        with self._lock:
            self.direct[ip] = (sock, time.monotonic())

    def _forget(self, ip: str) -> None:
        with self._lock:
            entry = self.direct.pop(ip, None)
        if entry is not None:
            entry[0].close()
