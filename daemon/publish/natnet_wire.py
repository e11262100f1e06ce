"""NatNet packets as each bitstream version lays them out: server info, model definitions,
frames, echo answers.

The layouts follow the parsers clients run: the NatNet SDK's PacketClient (natnetsdk on
PyPI), the `natnet` package and libmotioncapture. Versions differ in three places only,
for what we send: from 4.1 every data block and description carries its byte size, frames
carry an asset block and the precision (PTP) timestamp; from 4.2 a rigid-body description
carries a rotation after its offset; 3.x descriptions name no markers. Frames are the same
from 4.1 on (the SDK's 2025 client parses "4.1 to present" alike), so a client that asks
for 4.2 or later gets 4.1's frames and the newer descriptions. 4.0 is not served: the
SDK's own parsers disagree on whether its frames carry the precision timestamp.
"""

from __future__ import annotations

import socket
import struct
import time
from dataclasses import dataclass

import numpy as np

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
NAT_DISCONNECTBYTIMEOUT = 11
NAT_ECHOREQUEST = 12
NAT_ECHORESPONSE = 13
NAT_DISCOVERY = 14
NAT_UNRECOGNIZED_REQUEST = 100

NATNET_VERSION = (4, 1, 0, 0)
SERVER_VERSION = (1, 0, 0, 0)
APP_NAME = b"mocapd"
CLOCK_HZ = 1_000_000_000  # the tick stamps are time.monotonic_ns()
MAX_PAYLOAD = 65535  # the header's size field is a uint16
DEFAULT_VERSION = (4, 1)  # what the server info announces and multicast carries
TIMECODE_FPS = 30  # SMPTE timecode, 30 frames a second, non-drop

# marker parameter bits (NatNet's sMarker.params)
MARKER_OCCLUDED = 0x01
MARKER_PC_SOLVED = 0x02
MARKER_HAS_MODEL = 0x08
MARKER_UNLABELED = 0x10

MARKERSET_ID = 65535  # default model id of the live marker set's labelled markers

# z-up (ours) -> Motive's y-up: (x, y, z) -> (x, z, -y)
Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

def message(msg_id: int, payload: bytes) -> bytes:
    """One NatNet message: id, payload size, payload."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"NatNet payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    return struct.pack("<HH", msg_id, len(payload)) + payload


def parse_version(text: str) -> tuple[int, int] | None:
    """'4.2', '4.2.0.0' -> (4, 2); None when it is not a version number."""
    parts = text.strip().split(".")
    if not 2 <= len(parts) <= 4 or not all(p.isdigit() for p in parts):
        return None
    return int(parts[0]), int(parts[1])


def served(version: tuple[int, int]) -> bool:
    """The bitstream versions this server can send: 3.0, 3.1, 4.1 and 4.2 onwards."""
    return version in ((3, 0), (3, 1)) or (version[0] == 4 and version[1] >= 1)


def same_frames(a: tuple[int, int], b: tuple[int, int]) -> bool:
    """Whether two versions' frames are laid out alike (every 4.x from 4.1 on)."""
    return a == b or (a[0] == b[0] == 4 and min(a[1], b[1]) >= 1)


def _sized(version) -> bool:
    return version >= (4, 1)


def echo_response(request: bytes, received_ns: int) -> bytes:
    """NAT_ECHORESPONSE: the client's 8-byte stamp back, and the server's clock (ns, the
    tick frequency of the server info) at `received_ns`, the moment the client's arithmetic
    takes as the middle of its round trip."""
    stamp = request[4:12].ljust(8, b"\0")
    return message(NAT_ECHORESPONSE, stamp + struct.pack("<Q", received_ns))


def timecode(wall_ns: int, fps: float) -> tuple[int, int]:
    """SMPTE timecode of a UTC time, NatNet's packing (hours << 24 | minutes << 16 |
    seconds << 8 | frame, at TIMECODE_FPS), and the subframe: the capture frame's index
    within that timecode frame at the cameras' `fps`."""
    seconds, frac_ns = divmod(int(wall_ns), 1_000_000_000)
    day = seconds % 86400
    frame, within_ns = divmod(frac_ns * TIMECODE_FPS, 1_000_000_000)
    sub = int(within_ns / TIMECODE_FPS * fps / 1e9) if fps > TIMECODE_FPS else 0
    return (day // 3600) << 24 | (day // 60 % 60) << 16 | (day % 60) << 8 | frame, sub


def precision_timestamp(wall_ns: int) -> tuple[int, int]:
    """4.1's precision timestamp: UTC seconds since 1970 (mod 2^32) and nanoseconds, as a
    PTP clock counts them."""
    seconds, ns = divmod(int(wall_ns), 1_000_000_000)
    return seconds & 0xFFFFFFFF, ns


def server_info(data_port: int, multicast: bool, group: str) -> bytes:
    """NAT_SERVERINFO: sServerDescription as the SDK lays it out (279 bytes)."""
    payload = (APP_NAME.ljust(256, b"\0") + bytes(SERVER_VERSION) + bytes(NATNET_VERSION)
               + struct.pack("<QHB", CLOCK_HZ, data_port, 1 if multicast else 0)
               + socket.inet_aton(group))
    return message(NAT_SERVERINFO, payload)


_AXES = {"z": np.eye(3), "y": Y_UP}
_IDENTITY_Q = np.array([0.0, 0.0, 0.0, 1.0])


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
                      markerset=None, version: tuple[int, int] = DEFAULT_VERSION) -> bytes:
    """NAT_MODELDEF: the marker sets (unless turned off; `markerset` (name, marker names)
    adds the live marker set's), then the rigid bodies (BodyDef: name, id, markers in the
    body frame).

    Offsets are zero and the markers are given relative to the body's pivot, because
    clients (libmotioncapture) add the offset to every reported position."""
    M = axes(up_axis)
    sets = marker_set_names(bodies, markerset) if marker_sets else []
    parts = [struct.pack("<i", len(sets) + len(bodies))]

    def dataset(kind: int, desc: bytes) -> bytes:  # its byte size from 4.1 on
        return struct.pack("<ii", kind, len(desc)) + desc if _sized(version) else \
            struct.pack("<i", kind) + desc

    for name, names in sets:
        parts.append(dataset(0, name.encode("utf-8") + b"\0" + struct.pack("<i", len(names))
                             + b"".join(m.encode("utf-8") + b"\0" for m in names)))
    for b in bodies:
        markers = (np.asarray(b.markers, float) - np.asarray(b.pivot, float)) @ M.T
        k = len(markers)
        names = b"".join(f"Marker{j + 1}".encode() + b"\0" for j in range(k))
        parts.append(dataset(1, b.name.encode("utf-8") + b"\0"
                             + struct.pack("<iifff", int(b.id), -1, 0.0, 0.0, 0.0)
                             + (_IDENTITY_Q.astype("<f4").tobytes() if version >= (4, 2)
                                else b"")
                             + struct.pack("<i", k) + markers.astype("<f4").tobytes()
                             + np.zeros(k, "<i4").tobytes()
                             + (names if version >= (4, 0) else b"")))
    return message(NAT_MODELDEF, b"".join(parts))


def _block(count: int, data: bytes, sized: bool = True) -> bytes:
    """A data block: element count, byte size (from 4.1 on), the elements."""
    return (struct.pack("<ii", count, len(data)) if sized else struct.pack("<i", count)) + data


def _records(*columns) -> bytes:
    """Packed records (no padding, as NatNet lays them out) from per-field columns."""
    n = len(columns[0])
    return np.concatenate([np.ascontiguousarray(c).reshape(n, -1).view(np.uint8)
                           for c in columns], axis=1).tobytes()


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


def marker_sets_block(result, model: MarkerModel, M: np.ndarray | None,
                      only: frozenset | None = None) -> tuple[int, bytes]:
    """The frame's marker sets: each body's markers where it is tracked (the track's
    position when seen, else where the fitted pose puts it), zeros when it is not; the
    live marker set's markers where labelled this frame, zeros where not; then `all`.
    Nothing when the frame's bodies are not the model's. `only`: the set names a
    subscriber asked for (None: every set)."""
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
    if only is not None:
        parts = [part for part in parts if part[:part.index(b"\0")].decode("utf-8") in only]
    return len(parts), b"".join(parts)


@dataclass(frozen=True)
class View:
    """What one unicast subscriber asked for (Motive's SubscribeToData): rigid bodies by
    id (None: all), labelled markers, marker sets by name (None: all), the legacy list."""

    bodies: frozenset | None = None
    labeled: bool = True
    marker_sets: frozenset | None = None
    legacy: bool = True


EVERYTHING = View()


def frame_payload(result, up_axis: str = "z", legacy_unlabeled: bool = False,
                  t0_ns: int = 0, transmit_ns: int | None = None,
                  models_changed: bool = False, marker_model: MarkerModel | None = None,
                  markerset_id: int = MARKERSET_ID, version: tuple[int, int] = DEFAULT_VERSION,
                  timecode: tuple[int, int] = (0, 0), precision: tuple[int, int] = (0, 0),
                  recording: bool = False, view: View = EVERYTHING) -> bytes:
    """The NAT_FRAMEOFDATA payload for a FrameResult (daemon.capture.pipeline); with a
    MarkerModel, the bodies' (and the live marker set's) marker sets too. Markers the
    live marker set named (result.labelled) are labelled (markerset_id << 16 | index + 1)
    unless a body holds them. `timecode` and `precision` (see timecode() and
    precision_timestamp()) fill the suffix; `view` leaves out what a subscriber did not
    ask for."""
    M = axes(up_axis)
    turn = up_axis != "z"
    sized = _sized(version)
    p = result.poses
    keep = (np.ones(len(p.ids), bool) if view.bodies is None
            else np.isin(np.asarray(p.ids), list(view.bodies)))
    valid = np.asarray(p.valid, bool)[keep]
    n = len(valid)
    pos, q = np.asarray(p.position, float)[keep], np.asarray(p.quaternion, float)[keep]
    if turn:
        pos, q = pos @ M.T, rotate_quaternion(q, M)
    # rigid bodies, 38 bytes: id, x y z, qx qy qz qw, mean error, params (bit 0: valid);
    # an invalid body keeps a zero pose (its NaNs never reach the wire)
    rigid = _records(np.asarray(p.ids)[keep].astype("<i4"),
                     np.where(valid[:, None], pos, 0.0).astype("<f4"),
                     np.where(valid[:, None], q, _IDENTITY_Q).astype("<f4"),
                     np.where(valid, np.asarray(p.error_m)[keep], 0.0).astype("<f4"),
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
    legacy = (xyz[~is_label].astype("<f4") if legacy_unlabeled and view.legacy
              else np.zeros((0, 3), "<f4"))
    if not view.labeled:
        m = 0
    n_sets, sets = (marker_sets_block(result, marker_model, M if turn else None,
                                      view.marker_sets)
                    if marker_model is not None else (0, b""))
    # the size field is 16 bits: past ~2000 markers, send the bodies' markers first and as
    # many others as fit (the bodies and marker sets always go)
    blocks = 8 if version >= (4, 1) else 7
    fixed = (4 + blocks * (8 if sized else 4) + (54 if version >= (4, 1) else 46)
             + 38 * n + len(sets))
    legacy = legacy[:max(0, (MAX_PAYLOAD - fixed) // 2 // 12)]
    fit = max(0, (MAX_PAYLOAD - fixed - 12 * len(legacy)) // 26)
    if m > fit:
        kept = np.sort(np.argsort(~is_label, kind="stable")[:fit])
        labels, xyz, is_label, m = labels[kept], xyz[kept], is_label[kept], fit
    zeros = np.zeros(m, "<f4")
    labelled = _records(labels.astype("<u4"), xyz.astype("<f4"), zeros,
                        np.where(is_label, _LABELLED, _UNLABELLED).astype("<i2"),
                        zeros) if m else b""

    t_ns = int(result.t_ns)
    # timecode, subframe, timestamp (s), the three ticks, the precision (PTP) timestamp
    # seconds and fraction (from 4.1), params (bit 0: recording, bit 1: models changed),
    # and the end-of-data tag
    stamps = struct.pack("<IIdQQQ", *timecode, (t_ns - t0_ns) * 1e-9, t_ns,
                         int(result.arrival_ns),
                         int(transmit_ns if transmit_ns is not None else time.monotonic_ns()))
    params = (0x01 if recording else 0) | (0x02 if models_changed else 0)
    suffix = (stamps + (struct.pack("<II", *precision) if version >= (4, 1) else b"")
              + struct.pack("<hi", params, 0))
    head = struct.pack("<i", int(result.frame) & 0x7FFFFFFF)
    return (head
            + _block(n_sets, sets, sized)
            + _block(len(legacy), legacy.tobytes(), sized)  # legacy unlabelled markers
            + _block(n, rigid, sized)
            + _block(0, b"", sized)  # skeletons
            + (_block(0, b"", sized) if version >= (4, 1) else b"")  # assets (4.1)
            + _block(m, labelled, sized)
            + _block(0, b"", sized)  # force plates
            + _block(0, b"", sized)  # devices
            + suffix)


