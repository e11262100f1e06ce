"""The mocapd binary pose packet: encode and decode (UDP payload, and serial frame body).

Little-endian, fixed layout, no padding, so a microcontroller can cast it onto a packed
struct (mocapd_packet.h). docs/protocol.md is the reference; this module is its executable
form. A 24-byte header, then 36 bytes per body:

    header  u16 magic 0x434D ("MC")   u8 version (1)   u8 body count
            u32 frame number          i64 capture time, ns (the daemon's monotonic clock)
            u32 processing latency, ns (frame arrival to packet encoding, saturating)
            u32 flags (bit 0: a labelled-markers section follows the bodies; others 0)
    body    u16 id   u8 flags (bit 0: tracking valid)   u8 markers used
            f32 x, y, z (metres, world frame)   f32 qx, qy, qz, qw   f32 mean marker error (m)

With header flag bit 0 (a marker set is configured), the bodies are followed by the
labelled markers: a 4-byte section header and 16 bytes per marker:

    section u16 marker count          u16 marker-set size (markers in the set)
    marker  u16 index in the set      u8 confidence (0-255 for 0..1)   u8 flags (0)
            f32 x, y, z (metres, world frame)

Invalid bodies carry NaN pose fields, so a reader that ignores the flag still cannot use
a stale pose. Why a flag and not a new version: a packet without markers is byte for byte
what version 1 always was, so existing readers keep working wherever no marker set is
configured, and new readers read both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAGIC = 0x434D
VERSION = 1
HEADER = np.dtype([("magic", "<u2"), ("version", "u1"), ("count", "u1"), ("frame", "<u4"),
                   ("t_ns", "<i8"), ("latency_ns", "<u4"), ("flags", "<u4")])
BODY = np.dtype([("id", "<u2"), ("flags", "u1"), ("markers", "u1"), ("pos", "<f4", 3),
                 ("quat", "<f4", 4), ("error_m", "<f4")])
MARKERS_HEAD = np.dtype([("count", "<u2"), ("set_size", "<u2")])
MARKER = np.dtype([("index", "<u2"), ("confidence", "u1"), ("flags", "u1"),
                   ("pos", "<f4", 3)])
HEADER_SIZE = HEADER.itemsize  # 24
BODY_SIZE = BODY.itemsize  # 36
MARKERS_HEAD_SIZE = MARKERS_HEAD.itemsize  # 4
MARKER_SIZE = MARKER.itemsize  # 16
MAX_BODIES = 255
MAX_MARKERS = 65535
VALID = 1
HAS_MARKERS = 1  # header flag: the labelled-markers section follows the bodies


@dataclass(eq=False)
class Packet:
    """One decoded packet; arrays are per body."""

    frame: int
    t_ns: int
    latency_ns: int
    ids: np.ndarray  # (B,) uint16
    valid: np.ndarray  # (B,) bool
    markers: np.ndarray  # (B,) uint8
    position: np.ndarray  # (B, 3) float32
    quaternion: np.ndarray  # (B, 4) float32, x y z w
    error_m: np.ndarray  # (B,) float32
    # labelled markers (empty when the packet has no marker section)
    marker_index: np.ndarray | None = None  # (K,) uint16 index in the marker set
    marker_confidence: np.ndarray | None = None  # (K,) float32 0..1 (from the u8)
    marker_position: np.ndarray | None = None  # (K, 3) float32
    set_size: int = 0  # markers in the set; 0 when the packet has no marker section
    has_markers: bool = False

    def __post_init__(self) -> None:
        if self.marker_index is None:
            self.marker_index = np.zeros(0, np.uint16)
            self.marker_confidence = np.zeros(0, np.float32)
            self.marker_position = np.zeros((0, 3), np.float32)


def encode(frame: int, t_ns: int, latency_ns: int, ids, valid, markers, position, quaternion,
           error_m, labelled=None) -> bytes:
    """One packet for up to 255 bodies (arrays per body, as BodyPoses holds them).

    `labelled`: (set_size, index (K,), confidence (K,) 0..1, position (K, 3)) adds the
    labelled-markers section (header flag bit 0); None leaves the version-1 layout as is."""
    n = len(ids)
    if n > MAX_BODIES:
        raise ValueError(f"a packet carries at most {MAX_BODIES} bodies, got {n}")
    buf = np.zeros(1, HEADER)
    buf["magic"], buf["version"], buf["count"] = MAGIC, VERSION, n
    buf["frame"] = frame & 0xFFFFFFFF
    buf["t_ns"] = t_ns
    buf["latency_ns"] = min(max(int(latency_ns), 0), 0xFFFFFFFF)
    body = np.zeros(n, BODY)
    body["id"] = ids
    body["flags"] = np.where(np.asarray(valid, dtype=bool), VALID, 0)
    body["markers"] = np.minimum(np.asarray(markers), 255)
    body["pos"] = position
    body["quat"] = quaternion
    body["error_m"] = error_m
    if labelled is None:
        return buf.tobytes() + body.tobytes()
    set_size, index, confidence, xyz = labelled
    k = len(index)
    if k > MAX_MARKERS or not 0 <= set_size <= MAX_MARKERS:
        raise ValueError(f"a packet carries at most {MAX_MARKERS} markers, got {k}")
    buf["flags"] = HAS_MARKERS
    head = np.zeros(1, MARKERS_HEAD)
    head["count"], head["set_size"] = k, set_size
    mk = np.zeros(k, MARKER)
    mk["index"] = index
    mk["confidence"] = np.rint(np.clip(np.nan_to_num(np.asarray(confidence, np.float64)),
                                       0.0, 1.0) * 255)
    mk["pos"] = xyz
    return buf.tobytes() + body.tobytes() + head.tobytes() + mk.tobytes()


def decode(data: bytes) -> Packet:
    """A packet from bytes; ValueError when it is not one (wrong magic, version or size)."""
    if len(data) < HEADER_SIZE:
        raise ValueError(f"packet of {len(data)} bytes is shorter than the header")
    head = np.frombuffer(data, HEADER, count=1)[0]
    if head["magic"] != MAGIC or head["version"] != VERSION:
        raise ValueError("not a mocapd packet (magic or version)")
    n = int(head["count"])
    end = HEADER_SIZE + n * BODY_SIZE
    has_markers = bool(head["flags"] & HAS_MARKERS)
    if has_markers:
        if len(data) < end + MARKERS_HEAD_SIZE:
            raise ValueError(f"packet size {len(data)} leaves no room for its marker section")
        mh = np.frombuffer(data, MARKERS_HEAD, count=1, offset=end)[0]
        k, set_size = int(mh["count"]), int(mh["set_size"])
        if len(data) != end + MARKERS_HEAD_SIZE + k * MARKER_SIZE:
            raise ValueError(f"packet size {len(data)} does not match {n} bodies and "
                             f"{k} markers")
    elif len(data) != end:
        raise ValueError(f"packet size {len(data)} does not match {n} bodies")
    body = np.frombuffer(data, BODY, count=n, offset=HEADER_SIZE)
    out = Packet(int(head["frame"]), int(head["t_ns"]), int(head["latency_ns"]),
                 body["id"].copy(), (body["flags"] & VALID) > 0, body["markers"].copy(),
                 body["pos"].copy(), body["quat"].copy(), body["error_m"].copy())
    if has_markers:
        mk = np.frombuffer(data, MARKER, count=k, offset=end + MARKERS_HEAD_SIZE)
        out.marker_index = mk["index"].copy()
        out.marker_confidence = mk["confidence"].astype(np.float32) / 255
        out.marker_position = mk["pos"].copy()
        out.set_size, out.has_markers = set_size, True
    return out


# ---- serial framing: CRC-16 and COBS -------------------------------------------------------

def _crc_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint16)
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table[i] = crc & 0xFFFF
    return table


_CRC_TABLE = _crc_table().tolist()


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor)."""
    crc = 0xFFFF
    table = _CRC_TABLE
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[((crc >> 8) ^ byte) & 0xFF]
    return crc


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: no zero byte in the output (PacketSerial's COBS).

    Each block is a code byte (1 + the count of non-zero bytes that follow, at most 254)
    and those bytes; a code below 0xFF stands for a zero after its block, except at the end.
    """
    out = bytearray()
    start, n = 0, len(data)
    while True:
        zero = data.find(b"\x00", start, min(start + 254, n))
        end = zero if zero >= 0 else min(start + 254, n)
        out.append(end - start + 1)
        out += data[start:end]
        if zero >= 0:
            start = zero + 1
            if start == n:  # a trailing zero: an empty block closes the frame
                out.append(1)
                break
        else:
            start = end
            if end >= n:
                break
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of cobs_encode; ValueError on a malformed frame."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise ValueError("zero byte inside a COBS frame")
        end = i + code
        if end > n:
            raise ValueError("COBS frame truncated")
        out += data[i + 1:end]
        i = end
        if code < 0xFF and i < n:
            out.append(0)
    return bytes(out)


def serial_frame(payload: bytes) -> bytes:
    """payload + CRC-16 (little-endian), COBS-encoded, ending in the 0x00 delimiter."""
    crc = crc16(payload)
    return cobs_encode(payload + bytes([crc & 0xFF, crc >> 8])) + b"\x00"


def read_serial_frame(frame: bytes) -> bytes:
    """A COBS frame (without its delimiter) -> the payload; ValueError if the CRC is wrong."""
    raw = cobs_decode(frame)
    if len(raw) < 2:
        raise ValueError("serial frame too short")
    payload, crc = raw[:-2], raw[-2] | (raw[-1] << 8)
    if crc16(payload) != crc:
        raise ValueError("serial frame CRC mismatch")
    return payload
