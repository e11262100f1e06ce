"""The mocapd binary pose packet: encode and decode (UDP payload, and serial frame body).

Little-endian, fixed layout, no padding, so a microcontroller can cast it onto a packed
struct (mocapd_packet.h). docs/protocol.md is the reference; this module is its executable
form. A 24-byte header, then 36 bytes per body:

    header  u16 magic 0x434D ("MC")   u8 version (1)   u8 body count
            u32 frame number          i64 capture time, ns (the daemon's monotonic clock)
            u32 processing latency, ns (frame arrival to packet encoding, saturating)
            u32 flags (reserved, 0)
    body    u16 id   u8 flags (bit 0: tracking valid)   u8 markers used
            f32 x, y, z (metres, world frame)   f32 qx, qy, qz, qw   f32 mean marker error (m)

Invalid bodies carry NaN pose fields, so a reader that ignores the flag still cannot use
a stale pose.
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
HEADER_SIZE = HEADER.itemsize  # 24
BODY_SIZE = BODY.itemsize  # 36
MAX_BODIES = 255
VALID = 1


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


def encode(frame: int, t_ns: int, latency_ns: int, ids, valid, markers, position, quaternion,
           error_m) -> bytes:
    """One packet for up to 255 bodies (arrays per body, as BodyPoses holds them)."""
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
    return buf.tobytes() + body.tobytes()


def decode(data: bytes) -> Packet:
    """A packet from bytes; ValueError when it is not one (wrong magic, version or size)."""
    if len(data) < HEADER_SIZE:
        raise ValueError(f"packet of {len(data)} bytes is shorter than the header")
    head = np.frombuffer(data, HEADER, count=1)[0]
    if head["magic"] != MAGIC or head["version"] != VERSION:
        raise ValueError("not a mocapd packet (magic or version)")
    n = int(head["count"])
    if len(data) != HEADER_SIZE + n * BODY_SIZE:
        raise ValueError(f"packet size {len(data)} does not match {n} bodies")
    body = np.frombuffer(data, BODY, count=n, offset=HEADER_SIZE)
    return Packet(int(head["frame"]), int(head["t_ns"]), int(head["latency_ns"]),
                  body["id"].copy(), (body["flags"] & VALID) > 0, body["markers"].copy(),
                  body["pos"].copy(), body["quat"].copy(), body["error_m"].copy())


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
