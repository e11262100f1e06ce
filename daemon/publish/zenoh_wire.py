"""The binary messages nodes and the daemon exchange over Zenoh (docs/protocol.md).

Little-endian, fixed headers, no self-description: a 240 fps camera sends a message every
4 ms and each byte and microsecond of decoding shows in the latency. Every message starts
with a two-byte magic and a version, so a consumer can refuse what it does not know.

Blobs (`mocap/<rig>/<camera>/blobs`): one message per camera frame, times in ns on the
node's clock (the daemon maps them to its own, daemon.nodes.clock). Blob sets
(`mocap/<rig>/_nodes/<node>/blobs`, a node with `publish = "sets"`): the frames of one
trigger from all the node's cameras in one message, their fields as one table, then their
names and blobs: eight cameras at 240 fps are 240 messages a second rather than 1920, and
every message is a wake-up of the daemon's interpreter. Clock exchanges
(`mocap/<rig>/_clock/ping`, `mocap/<rig>/_nodes/<node>/clock`): the four NTP-style stamps.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

import numpy as np

VERSION = 1
BLOBS_MAGIC = b"MB"
PING_MAGIC = b"MQ"
PONG_MAGIC = b"MR"
POSE_MAGIC = b"MP"
SETS_MAGIC = b"MS"

# magic, version, flags, boot, seq, index, t_ns, arrival_ns, sent_ns, device_time_ns,
# device_frame_id, blob count
BLOBS_HEAD = struct.Struct("<2sBBIIIqqqqqH")
BLOB = np.dtype([("u", "<f4"), ("v", "<f4"), ("area", "<f4"), ("peak", "<f4")])
# magic, version, flags, boot, seq, sent_ns, camera count
SETS_HEAD = struct.Struct("<2sBBIIqH")
SET_SHORT = 1  # flags: the set left without a camera it waited for (set_wait_ms passed)
# per frame: index, t_ns, arrival_ns, device_time_ns, device_frame_id, blob count; then per
# frame its camera's name (a u8 length and ASCII), then every frame's blobs in order
SETS_FRAME = np.dtype([("index", "<u4"), ("t_ns", "<i8"), ("arrival_ns", "<i8"),
                       ("device_time_ns", "<i8"), ("device_frame_id", "<i8"), ("n", "<u2")])
PING = struct.Struct("<2sBBIq")  # magic, version, flags, seq, t1 (daemon clock)
# magic, version, flags, boot, seq, t1 (daemon clock, echoed), t2, t3 (node clock)
PONG = struct.Struct("<2sBBIIqqq")
# magic, version, flags (bit 0: valid), body id, frame, t_ns, latency_ns, markers,
# x y z (m), qx qy qz qw, error (m)
POSE = struct.Struct("<2sBBHIqqH3f4ff")


class WireError(ValueError):
    """A message that is not what its key says (another version, cut short)."""


class BlobsMessage(NamedTuple):
    """One camera frame's blobs as a node publishes them (times on the node's clock). A
    named tuple: the daemon makes 7680 of them a second with 32 remote cameras."""

    boot: int  # the node process's random id: a new one means it restarted
    seq: int  # the node's count of messages (for this camera, or of sets)
    index: int  # the camera's frame count since it opened
    t_ns: int  # the node's estimate of the capture time
    arrival_ns: int  # when the node got the frame
    sent_ns: int  # when the node published it
    device_time_ns: int  # the camera's own timestamp (-1: none)
    device_frame_id: int  # the camera's own counter (-1: none)
    uv: np.ndarray  # (N, 2) distorted pixels
    area: np.ndarray
    peak: np.ndarray
    flags: int = 0  # of a blob-sets message: SET_SHORT


def _blob_bytes(uv, area, peak) -> bytes:
    n = len(uv)
    if n > 65535:
        raise ValueError(f"{n} blobs in one frame: at most 65535 fit a message")
    body = np.empty(n, BLOB)
    uv = np.asarray(uv)
    body["u"], body["v"] = uv[:, 0] if n else (), uv[:, 1] if n else ()
    body["area"], body["peak"] = area, peak
    return body.tobytes()


def _blobs(data: bytes, n: int, at: int):
    """uv (N, 2), area, peak in float64 from n blob records at offset `at`; a NaN or
    infinity (no detector makes one) is refused here rather than tracked."""
    if not np.isfinite(np.frombuffer(data, "<f4", 4 * n, at)).all():
        raise WireError("a message with non-finite blob values (NaN or infinity)")
    body = np.frombuffer(data, BLOB, n, at)
    uv = np.empty((n, 2), np.float64)
    uv[:, 0], uv[:, 1] = body["u"], body["v"]
    return uv, body["area"].astype(np.float64), body["peak"].astype(np.float64)


def encode_blobs(boot: int, seq: int, index: int, t_ns: int, arrival_ns: int, sent_ns: int,
                 device_time_ns: int, device_frame_id: int, uv, area, peak) -> bytes:
    body = _blob_bytes(uv, area, peak)
    head = BLOBS_HEAD.pack(BLOBS_MAGIC, VERSION, 0, boot & 0xFFFFFFFF, seq & 0xFFFFFFFF,
                           index & 0xFFFFFFFF, t_ns, arrival_ns, sent_ns, device_time_ns,
                           device_frame_id, len(uv))
    return head + body


def decode_blobs(data: bytes) -> BlobsMessage:
    if len(data) < BLOBS_HEAD.size:
        raise WireError(f"a blobs message of {len(data)} bytes is shorter than its header")
    (magic, version, _, boot, seq, index, t_ns, arrival, sent, device, fid,
     n) = BLOBS_HEAD.unpack_from(data)
    if magic != BLOBS_MAGIC or version != VERSION:
        raise WireError(f"not a version {VERSION} blobs message ({magic!r} v{version})")
    if len(data) != BLOBS_HEAD.size + n * BLOB.itemsize:
        raise WireError(f"a blobs message says {n} blobs but has {len(data)} bytes")
    uv, area, peak = _blobs(data, n, BLOBS_HEAD.size)
    return BlobsMessage(boot, seq, index, t_ns, arrival, sent, device, fid, uv, area, peak)


def encode_sets(boot: int, seq: int, sent_ns: int, frames, flags: int = 0) -> bytes:
    """One message of a node's frames: `frames` are (camera name as bytes, index, t_ns,
    arrival_ns, device_time_ns, device_frame_id, uv, area, peak). The frames' fixed fields
    come first as one table, then the names, then every frame's blobs back to back: the
    daemon decodes a message with a handful of array calls, not a handful per frame."""
    table = np.empty(len(frames), SETS_FRAME)
    names, blobs = [], []
    for k, (name, index, t_ns, arrival, device, fid, uv, area, peak) in enumerate(frames):
        if len(name) > 255:
            raise ValueError(f"camera name {name!r} is longer than 255 bytes")
        table[k] = (index & 0xFFFFFFFF, t_ns, arrival, device, fid, len(uv))
        names += [bytes((len(name),)), name]
        blobs.append(_blob_bytes(uv, area, peak))
    return b"".join([SETS_HEAD.pack(SETS_MAGIC, VERSION, flags, boot & 0xFFFFFFFF,
                                    seq & 0xFFFFFFFF, sent_ns, len(frames)),
                     table.tobytes(), *names, *blobs])


class BlobSets(NamedTuple):
    """A blob-sets message as arrays (decode_sets_arrays): what the daemon's hub maps and
    hands to the multiplexer in one call, without an object per frame first."""

    boot: int
    seq: int
    sent_ns: int
    flags: int
    names: list[str]  # per frame, its camera's name
    table: np.ndarray  # per frame: SETS_FRAME's fields
    uv: np.ndarray  # (total blobs, 2), every frame's blobs in order
    area: np.ndarray
    peak: np.ndarray
    ends: list[int]  # per frame, where its blobs end in uv, area and peak


def decode_sets(data: bytes) -> list[tuple[str, BlobsMessage]]:
    """(camera name, its frame) for every frame of a blob-sets message (docs/protocol.md)."""
    m = decode_sets_arrays(data)
    out, a = [], 0
    rows = m.table.tolist()
    for name, (index, t_ns, arrival, device, fid, _n), b in zip(m.names, rows, m.ends,
                                                                strict=True):
        out.append((name, BlobsMessage(m.boot, m.seq, index, t_ns, arrival, m.sent_ns, device,
                                       fid, m.uv[a:b], m.area[a:b], m.peak[a:b], m.flags)))
        a = b
    return out


def decode_sets_arrays(data: bytes) -> BlobSets:
    """A blob-sets message's frames as one table and its blobs as three arrays: a handful
    of numpy calls whatever the number of frames (the names are the one per-frame loop)."""
    size = len(data)
    if size < SETS_HEAD.size:
        raise WireError(f"a blob-sets message of {size} bytes is shorter than its header")
    magic, version, flags, boot, seq, sent, count = SETS_HEAD.unpack_from(data)
    if magic != SETS_MAGIC or version != VERSION:
        raise WireError(f"not a version {VERSION} blob-sets message ({magic!r} v{version})")
    at = SETS_HEAD.size + count * SETS_FRAME.itemsize
    if at > size:
        raise WireError(f"a blob-sets message of {size} bytes ends inside its {count} frames")
    table = np.frombuffer(data, SETS_FRAME, count, SETS_HEAD.size)
    names = []
    for _ in range(count):
        end = at + 1 + (data[at] if at < size else 0)
        names.append(data[at + 1:end].decode("ascii", "replace"))
        at = end
    counts = table["n"].astype(np.int64)
    total = int(counts.sum())
    if at + total * BLOB.itemsize != size:
        raise WireError(f"a blob-sets message of {size} bytes does not hold the {total} "
                        "blobs it says")
    uv, area, peak = _blobs(data, total, at)
    return BlobSets(boot, seq, sent, flags, names, table, uv, area, peak,
                    np.cumsum(counts).tolist())


def encode_ping(seq: int, t1_ns: int) -> bytes:
    return PING.pack(PING_MAGIC, VERSION, 0, seq & 0xFFFFFFFF, t1_ns)


def decode_ping(data: bytes) -> tuple[int, int]:
    """(seq, t1) of a ping."""
    if len(data) != PING.size:
        raise WireError(f"a ping of {len(data)} bytes (want {PING.size})")
    magic, version, _, seq, t1 = PING.unpack(data)
    if magic != PING_MAGIC or version != VERSION:
        raise WireError(f"not a version {VERSION} ping ({magic!r} v{version})")
    return seq, t1


def encode_pong(boot: int, seq: int, t1_ns: int, t2_ns: int, t3_ns: int) -> bytes:
    return PONG.pack(PONG_MAGIC, VERSION, 0, boot & 0xFFFFFFFF, seq, t1_ns, t2_ns, t3_ns)


def decode_pong(data: bytes) -> tuple[int, int, int, int, int]:
    """(boot, seq, t1, t2, t3) of a pong."""
    if len(data) != PONG.size:
        raise WireError(f"a pong of {len(data)} bytes (want {PONG.size})")
    magic, version, _, boot, seq, t1, t2, t3 = PONG.unpack(data)
    if magic != PONG_MAGIC or version != VERSION:
        raise WireError(f"not a version {VERSION} pong ({magic!r} v{version})")
    return boot, seq, t1, t2, t3


def encode_pose(body_id: int, frame: int, t_ns: int, latency_ns: int, valid: bool,
                markers: int, position, quaternion, error_m: float) -> bytes:
    return POSE.pack(POSE_MAGIC, VERSION, 1 if valid else 0, body_id, frame & 0xFFFFFFFF,
                     t_ns, latency_ns, markers, *map(float, position),
                     *map(float, quaternion), float(error_m))


def decode_pose(data: bytes) -> dict:
    """A pose message as a dict (what a Python consumer needs; docs/protocol.md)."""
    if len(data) != POSE.size:
        raise WireError(f"a pose message of {len(data)} bytes (want {POSE.size})")
    (magic, version, flags, body, frame, t_ns, latency, markers, x, y, z, qx, qy, qz, qw,
     err) = POSE.unpack(data)
    if magic != POSE_MAGIC or version != VERSION:
        raise WireError(f"not a version {VERSION} pose message ({magic!r} v{version})")
    return {"id": body, "frame": frame, "t_ns": t_ns, "latency_ns": latency,
            "valid": bool(flags & 1), "markers": markers, "position": (x, y, z),
            "quaternion": (qx, qy, qz, qw), "error_m": err}
