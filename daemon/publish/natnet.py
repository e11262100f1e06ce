"""NatNet 4.1 server: what OptiTrack's Motive streams, so NatNet clients read mocapd unchanged.

Why 4.1 and not the newest: clients written against 4.1 (libmotioncapture, the `natnet`
package, lab scripts built on NatNet SDK 4.1's PacketClient) cannot parse 4.2's rigid-body
descriptions (4.2 inserted a quaternion), while every newer client still reads 4.1.

The protocol, as the SDK's packet parsers read it (all little-endian; every message starts
with uint16 message id and uint16 payload size):

- command port (UDP, default 1510): a client sends NAT_CONNECT and gets NAT_SERVERINFO
  (application name, versions, the clock frequency of the frame's tick stamps, the data
  port, whether data is multicast, the group); NAT_REQUEST_MODELDEF gets NAT_MODELDEF (a
  marker set per body and "all", then the rigid bodies: name, id, parent, offset, marker
  positions; with a marker set configured, one more marker set named after it with its
  markers by name, before "all"); NAT_KEEPALIVE subscribes the
  sending address to unicast frames for `keepalive_timeout_s`; NAT_REQUEST_FRAMEOFDATA gets
  the latest frame; NAT_DISCONNECT unsubscribes.
- frames (NAT_FRAMEOFDATA) go to the multicast group on the data port (default
  239.255.42.99:1511) and to every subscribed unicast address. With multicast off they
  also go to the data port of each connected client's address, where libmotioncapture
  listens without sending keep-alives (dropped when that port refuses them). Each carries
  the frame number, the marker sets, rigid bodies (id, position, quaternion x y z w, mean
  marker error, tracking-valid flag), labelled markers (a body's markers as (body id << 16
  | member); a marker the marker set named as (markerset_id << 16 | its index in the set
  + 1); the others flagged unlabelled with their track id), a timestamp and three
  clock ticks (mid-exposure, data received, transmit; nanoseconds of the monotonic clock,
  frequency 1e9) from which clients compute camera-to-client latency.

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

import numpy as np

from daemon.publish.base import Publisher

log = logging.getLogger("mocapd.publish")

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_UNRECOGNIZED_REQUEST = 100

NATNET_VERSION = (4, 1, 0, 0)
SERVER_VERSION = (1, 0, 0, 0)
APP_NAME = b"mocapd"
CLOCK_HZ = 1_000_000_000  # the tick stamps are time.monotonic_ns()
MAX_PAYLOAD = 65535  # the header's size field is a uint16
DIRECT_GRACE_S = 3.0  # a keep-alive-less unicast client has this long to open its data port

# marker parameter bits (NatNet's sMarker.params)
MARKER_OCCLUDED = 0x01
MARKER_PC_SOLVED = 0x02
MARKER_HAS_MODEL = 0x08
MARKER_UNLABELED = 0x10

MARKERSET_ID = 65535  # default model id of the live marker set's labelled markers

# z-up (ours) -> Motive's y-up: (x, y, z) -> (x, z, -y)
Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

# commands Motive answers that mean nothing here (no timeline, no recording): acknowledged
_NOOP_COMMANDS = ("timelineplay", "timelinestop", "setplaybackcurrentframe", "subscribetodata",
                  "subscribebyid", "subscribeddataonly", "startrecording", "stoprecording",
                  "livemode", "editmode", "setrecordtakename", "setcurrentsession")


def message(msg_id: int, payload: bytes) -> bytes:
    """One NatNet message: id, payload size, payload."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"NatNet payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    return struct.pack("<HH", msg_id, len(payload)) + payload


def server_info(data_port: int, multicast: bool, group: str) -> bytes:
    """NAT_SERVERINFO: sServerDescription as the SDK lays it out (279 bytes)."""
    payload = (APP_NAME.ljust(256, b"\0") + bytes(SERVER_VERSION) + bytes(NATNET_VERSION)
               + struct.pack("<QHB", CLOCK_HZ, data_port, 1 if multicast else 0)
               + socket.inet_aton(group))
    return message(NAT_SERVERINFO, payload)


_AXES = {"z": np.eye(3), "y": Y_UP}


def axes(up_axis: str) -> np.ndarray:
    if up_axis not in _AXES:
        raise ValueError(f"up_axis must be 'z' or 'y', got {up_axis!r}")
    return _AXES[up_axis]


def rotate_quaternion(q: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Quaternions (x, y, z, w) of M R M^T: the rotation axis turns with M, angle unchanged."""
    out = np.empty_like(q)
    out[..., :3] = q[..., :3] @ M.T
    out[..., 3] = q[..., 3]
    return out


def marker_set_names(bodies, markerset=None) -> list[tuple[str, list[str]]]:
    """Motive's marker sets: one per rigid body (its markers, `Marker1`...), the live
    marker set (name, marker names) if one is configured, and `all`."""
    sets = [(b.name, [f"Marker{j + 1}" for j in range(len(b.markers))]) for b in bodies]
    if markerset is not None:
        sets.append((markerset[0], list(markerset[1])))
    if sets:
        sets.append(("all", [f"{name}_{m}" for name, ms in sets for m in ms]))
    return sets


def model_definitions(bodies, up_axis: str = "z", marker_sets: bool = True,
                      markerset=None) -> bytes:
    """NAT_MODELDEF: the marker sets (unless turned off; `markerset` (name, marker names)
    adds the live marker set's), then the rigid bodies (BodyDef: name, id, markers in the
    body frame).

    Offsets are zero and the markers are given relative to the body's pivot, because
    clients (libmotioncapture) add the offset to every reported position."""
    M = axes(up_axis)
    sets = marker_set_names(bodies, markerset) if marker_sets else []
    parts = [struct.pack("<i", len(sets) + len(bodies))]
    for name, names in sets:
        desc = (name.encode("utf-8") + b"\0" + struct.pack("<i", len(names))
                + b"".join(m.encode("utf-8") + b"\0" for m in names))
        parts.append(struct.pack("<ii", 0, len(desc)) + desc)  # type 0: marker set
    for b in bodies:
        markers = (np.asarray(b.markers, float) - np.asarray(b.pivot, float)) @ M.T
        k = len(markers)
        desc = (b.name.encode("utf-8") + b"\0"
                + struct.pack("<iifffi", int(b.id), -1, 0.0, 0.0, 0.0, k)
                + markers.astype("<f4").tobytes()
                + np.zeros(k, "<i4").tobytes()
                + b"".join(f"Marker{j + 1}".encode() + b"\0" for j in range(k)))
        parts.append(struct.pack("<ii", 1, len(desc)) + desc)  # type 1: rigid body
    return message(NAT_MODELDEF, b"".join(parts))


def _block(count: int, data: bytes) -> bytes:
    """A 4.1 data block: element count, byte size, the elements."""
    return struct.pack("<ii", count, len(data)) + data


def _records(*columns) -> bytes:
    """Packed records (no padding, as NatNet lays them out) from per-field columns."""
    n = len(columns[0])
    return np.concatenate([np.ascontiguousarray(c).reshape(n, -1).view(np.uint8)
                           for c in columns], axis=1).tobytes()


_IDENTITY_Q = np.array([0.0, 0.0, 0.0, 1.0])
_FIXED_BYTES = 4 + 8 * 8 + 54  # frame number, eight block headers, the suffix
_LABELLED = MARKER_PC_SOLVED | MARKER_HAS_MODEL
_UNLABELLED = MARKER_PC_SOLVED | MARKER_UNLABELED


class MarkerModel:
    """The bodies' markers relative to their pivots, padded to (B, K, 3), for the frames'
    marker sets; and the live marker set's name and size, if one is configured."""

    def __init__(self, bodies, markerset=None) -> None:
        self.set_name = None if markerset is None else markerset[0].encode("utf-8") + b"\0"
        self.set_size = 0 if markerset is None else len(markerset[1])
        self.ids = np.array([int(b.id) for b in bodies], np.int64)
        self.names = [b.name.encode("utf-8") + b"\0" for b in bodies]
        self.counts = np.array([len(b.markers) for b in bodies], np.int64)
        k = int(self.counts.max(initial=0))
        self.local = np.zeros((len(bodies), k, 3))
        for i, b in enumerate(bodies):
            self.local[i, :len(b.markers)] = np.asarray(b.markers, float) - b.pivot


def marker_sets_block(result, model: MarkerModel, M: np.ndarray | None) -> tuple[int, bytes]:
    """The frame's marker sets: each body's markers where it is tracked (the track's
    position when seen, else where the fitted pose puts it), zeros when it is not; the
    live marker set's markers where labelled this frame, zeros where not; then `all`.
    Nothing when the frame's bodies are not the model's."""
    p = result.poses
    if (not len(model.ids) and model.set_name is None) or not np.array_equal(
            np.asarray(p.ids), model.ids):
        return 0, b""
    valid = np.asarray(p.valid, bool)
    k = model.local.shape[1]
    xyz = np.einsum("bij,bkj->bki", np.asarray(p.rotation, float), model.local)
    xyz += np.asarray(p.position, float)[:, None, :]
    tracks = np.asarray(p.tracks)[:, :k]
    tr = result.tracks
    ids = np.asarray(tr.ids)
    if len(ids) and (tracks >= 0).any():
        at = np.minimum(np.searchsorted(ids, tracks), len(ids) - 1)  # track ids are sorted
        hit = (tracks >= 0) & (ids[at] == tracks) & np.asarray(tr.seen, bool)[at]
        xyz[hit] = np.asarray(tr.xyz)[at[hit]]
    xyz[~valid] = 0.0
    if M is not None:
        xyz = xyz @ M.T
    xyz = np.nan_to_num(xyz).astype("<f4")
    parts = [name + struct.pack("<i", c) + xyz[i, :c].tobytes()
             for i, (name, c) in enumerate(zip(model.names, model.counts, strict=True))]
    chunks = [xyz[i, :c] for i, c in enumerate(model.counts)]
    if model.set_name is not None:
        named = np.zeros((model.set_size, 3))
        lab = getattr(result, "labelled", None)
        if lab is not None and len(lab.index):
            ok = np.asarray(lab.index) < model.set_size  # a set swapped by a reload
            named[np.asarray(lab.index)[ok]] = np.asarray(lab.xyz)[ok]
        if M is not None:
            named = named @ M.T
        named = named.astype("<f4")
        parts.append(model.set_name + struct.pack("<i", model.set_size) + named.tobytes())
        chunks.append(named)
    everything = np.concatenate(chunks).astype("<f4")
    parts.append(b"all\0" + struct.pack("<i", len(everything)) + everything.tobytes())
    return len(parts), b"".join(parts)


def frame_payload(result, up_axis: str = "z", legacy_unlabeled: bool = False,
                  t0_ns: int = 0, transmit_ns: int | None = None,
                  models_changed: bool = False, marker_model: MarkerModel | None = None,
                  markerset_id: int = MARKERSET_ID) -> bytes:
    """The NAT_FRAMEOFDATA payload for a FrameResult (daemon.pipeline); with a
    MarkerModel, the bodies' (and the live marker set's) marker sets too. Markers the
    live marker set named (result.labelled) are labelled (markerset_id << 16 | index + 1)
    unless a body holds them."""
    M = axes(up_axis)
    turn = up_axis != "z"
    p = result.poses
    valid = np.asarray(p.valid, bool)
    n = len(valid)
    pos, q = np.asarray(p.position, float), np.asarray(p.quaternion, float)
    if turn:
        pos, q = pos @ M.T, rotate_quaternion(q, M)
    # rigid bodies, 38 bytes: id, x y z, qx qy qz qw, mean error, params (bit 0: valid);
    # an invalid body keeps a zero pose (its NaNs never reach the wire)
    rigid = _records(np.asarray(p.ids).astype("<i4"),
                     np.where(valid[:, None], pos, 0.0).astype("<f4"),
                     np.where(valid[:, None], q, _IDENTITY_Q).astype("<f4"),
                     np.where(valid, p.error_m, 0.0).astype("<f4"),
                     valid.astype("<i2")) if n else b""

    # labelled markers, 26 bytes: id, x y z, size, params, residual. The seen tracks; those
    # a body holds are (body id << 16 | member), the others unlabelled with their track id
    tr = result.tracks
    seen = np.asarray(tr.seen, bool)
    ids, xyz = np.asarray(tr.ids)[seen], np.asarray(tr.xyz)[seen]
    if turn:
        xyz = xyz @ M.T
    m = len(ids)
    labels = ids & 0xFFFF
    is_label = np.zeros(m, bool)
    tracks = np.asarray(p.tracks)
    held = tracks >= 0
    if m and held.any():
        member = (np.asarray(p.ids, np.int64)[:, None] << 16) | np.arange(1, held.shape[1] + 1)
        tid = tracks[held]
        at = np.minimum(np.searchsorted(ids, tid), m - 1)  # track ids are sorted
        hit = ids[at] == tid
        labels[at[hit]] = member[held][hit]
        is_label[at[hit]] = True
    lab = getattr(result, "labelled", None)
    if m and lab is not None and len(lab.index):
        tid = np.asarray(lab.track)
        at = np.minimum(np.searchsorted(ids, tid), m - 1)
        hit = (ids[at] == tid) & ~is_label[at]
        labels[at[hit]] = (int(markerset_id) << 16) | (np.asarray(lab.index)[hit] + 1)
        is_label[at[hit]] = True
    legacy = xyz[~is_label].astype("<f4") if legacy_unlabeled else np.zeros((0, 3), "<f4")
    n_sets, sets = (marker_sets_block(result, marker_model, M if turn else None)
                    if marker_model is not None else (0, b""))
    # the size field is 16 bits: past ~2000 markers, send the bodies' markers first and as
    # many others as fit (the bodies and marker sets always go)
    fixed = _FIXED_BYTES + 38 * n + len(sets)
    legacy = legacy[:max(0, (MAX_PAYLOAD - fixed) // 2 // 12)]
    fit = max(0, (MAX_PAYLOAD - fixed - 12 * len(legacy)) // 26)
    if m > fit:
        keep = np.sort(np.argsort(~is_label, kind="stable")[:fit])
        labels, xyz, is_label, m = labels[keep], xyz[keep], is_label[keep], fit
    zeros = np.zeros(m, "<f4")
    labelled = _records(labels.astype("<u4"), xyz.astype("<f4"), zeros,
                        np.where(is_label, _LABELLED, _UNLABELLED).astype("<i2"),
                        zeros) if m else b""

    t_ns = int(result.t_ns)
    # timecode, subframe, timestamp (s), the three ticks, the precision (PTP) timestamp
    # seconds and fraction that 4.1 added (0: none), params (bit 1: models changed), and
    # the end-of-data tag
    suffix = struct.pack("<IIdQQQIIhi", 0, 0, (t_ns - t0_ns) * 1e-9, t_ns,
                         int(result.arrival_ns),
                         int(transmit_ns if transmit_ns is not None else time.monotonic_ns()),
                         0, 0, 0x02 if models_changed else 0, 0)
    head = struct.pack("<i", int(result.frame) & 0x7FFFFFFF)
    body = (head
            + _block(n_sets, sets)
            + _block(len(legacy), legacy.tobytes())  # legacy unlabelled markers
            + _block(n, rigid)
            + _block(0, b"")  # skeletons
            + _block(0, b"")  # assets (4.1)
            + _block(m, labelled)
            + _block(0, b"")  # force plates
            + _block(0, b"")  # devices
            + suffix)
    return body


class NatNetPublisher(Publisher):
    """Serves NatNet: answers the command port, sends frames by multicast and unicast."""

    # open servers by (interface, command port). A reload starts the new publisher while
    # the old one still runs (daemon.pipeline): the new one takes over the old one's command
    # socket and clients, so no request goes unanswered and no client has to connect again
    # (libmotioncapture never does)
    _live: dict[tuple, NatNetPublisher] = {}
    _live_lock = threading.Lock()

    def __init__(self, bodies=(), interface: str = "0.0.0.0", command_port: int = 1510,
                 data_port: int = 1511, multicast: bool = True,
                 group: str = "239.255.42.99", up_axis: str = "z", ttl: int = 1,
                 rate_hz: float = 0.0, legacy_unlabeled: bool = False,
                 keepalive_timeout_s: float = 10.0, name: str = "natnet",
                 marker_sets: bool = True, markerset=None,
                 markerset_id: int = MARKERSET_ID) -> None:
        """`markerset`: (name, marker names) of the live marker set, if one is configured;
        its labelled markers carry model id `markerset_id`."""
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
        self._cmd_thread: threading.Thread | None = None
        self._cmd_stop = threading.Event()
        self.markerset, self.markerset_id = markerset, markerset_id
        self._modeldef = model_definitions(self.bodies, up_axis, marker_sets, markerset)
        self._marker_model = MarkerModel(self.bodies, markerset) if marker_sets else None
        self._info = server_info(data_port, multicast, group)

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
        self.cmd_sock, self.data_sock = cmd, data
        with self._lock:
            self.subscribers.update(subscribers)
        if not self.multicast:
            for ip in direct_ips:
                self._direct(ip)
        self._cmd_stop.clear()
        self._cmd_thread = threading.Thread(target=self._serve, name=f"{self.name}-cmd",
                                            daemon=True)
        self._cmd_thread.start()
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

    def status(self) -> dict:
        st = super().status()
        with self._lock:
            st["unicast_clients"] = len(self.subscribers) + len(self.direct)
        return st

    # ---- frames ----------------------------------------------------------------------------

    def send(self, result) -> None:
        cmd = self.cmd_sock
        if cmd is None:  # handed over to the server that replaced this one
            return
        first = self.t0_ns is None
        if first:
            self.t0_ns = int(result.t_ns)
        data = message(NAT_FRAMEOFDATA, frame_payload(
            result, self.up_axis, self.legacy_unlabeled, self.t0_ns, models_changed=first,
            marker_model=self._marker_model, markerset_id=self.markerset_id))
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
            targets = list(self.subscribers)
            direct = list(self.direct.items())
        for addr in targets:
            try:
                cmd.sendto(data, addr)
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

    # ---- the command port ------------------------------------------------------------------

    def _serve(self) -> None:
        sock = self.cmd_sock
        while not self._cmd_stop.is_set():
            try:
                data, addr = sock.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError:
                if self._cmd_stop.is_set():
                    return
                continue
            try:
                reply = self.handle(data, addr)
            except Exception as exc:  # noqa: BLE001 - a bad request must not end the server
                log.warning("%s: bad request from %s:%d: %s", self.name, *addr, exc)
                continue
            if reply:
                try:
                    sock.sendto(reply, addr)
                except OSError:
                    pass

    def handle(self, data: bytes, addr) -> bytes | None:
        """The reply to one command-port datagram (None: no reply)."""
        if len(data) < 4:
            return None
        msg_id, size = struct.unpack_from("<HH", data)
        self.requests += 1
        if msg_id == NAT_CONNECT:  # a new session: no frames until its keep-alives
            with self._lock:
                self.subscribers.pop(addr, None)
            if not self.multicast:
                self._direct(addr[0])
            return self._info
        if msg_id == NAT_KEEPALIVE:
            with self._lock:
                self.subscribers[addr] = time.monotonic()
            return None
        if msg_id == NAT_REQUEST_MODELDEF:
            return self._modeldef
        if msg_id == NAT_REQUEST_FRAMEOFDATA:
            return self.latest
        if msg_id == NAT_DISCONNECT:
            with self._lock:
                self.subscribers.pop(addr, None)
            self._forget(addr[0])
            return None
        if msg_id == NAT_REQUEST:
            text = data[4:4 + size].split(b"\0", 1)[0].decode("utf-8", "replace")
            return self._command(text)
        return message(NAT_UNRECOGNIZED_REQUEST, b"")

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

    def _command(self, text: str) -> bytes:
        """NAT_RESPONSE to a command string: 0 for what we support or ignore, -1 otherwise."""
        word, _, arg = text.partition(",")
        word = word.strip().lower()
        if word == "bitstream":
            if not arg.strip():  # a query: the SDK clients read the version from the text
                return message(NAT_RESPONSE, b"Bitstream,%d.%d\0" % NATNET_VERSION[:2])
            ok = arg.strip() in ("4.1", "4.1.0", "4.1.0.0")
            return message(NAT_RESPONSE, struct.pack("<i", 0 if ok else -1))
        if word in _NOOP_COMMANDS:
            return message(NAT_RESPONSE, struct.pack("<i", 0))
        return message(NAT_UNRECOGNIZED_REQUEST, b"")
