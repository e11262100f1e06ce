"""VRPN's wire format, as a tracker server speaks it: cookies, message headers and padding,
sender and type descriptions, the client's UDP lob, and a frame's Pos_Quat messages packed
at once.

Apart from daemon/publish/vrpn.py (the server: sockets, clients, the publisher), whose
docstring lays the protocol out; these are pure functions on bytes and arrays, so the
format is tested without a socket.
"""

from __future__ import annotations

import struct
import time

import numpy as np

MAGIC = b"vrpn: ver. 07.35"
MAGIC_MAJOR = b"vrpn: ver. 07."  # minor versions interoperate
COOKIE_SIZE = 24
HEADER_SIZE = 24
ALIGN = 8

SENDER_DESCRIPTION = -1
TYPE_DESCRIPTION = -2
UDP_DESCRIPTION = -3
LOG_DESCRIPTION = -4

POS_QUAT = "vrpn_Tracker Pos_Quat"
PING = "vrpn_Base ping_message"
PONG = "vrpn_Base pong_message"
OUR_TYPES = (POS_QUAT, PONG)  # our type ids are the indices
UDP_MAX = 1472  # VRPN's UDP buffer: one Ethernet MTU

POSE_MESSAGE = np.dtype([("len", ">i4"), ("sec", ">i4"), ("usec", ">i4"), ("sender", ">i4"),
                         ("type", ">i4"), ("seq", ">i4"), ("sensor", ">i4"), ("pad", ">i4"),
                         ("pos", ">f8", 3), ("quat", ">f8", 4)])  # 88 bytes


def cookie(log_mode: int = 0) -> bytes:
    return (MAGIC + b"  " + bytes([48 + log_mode])).ljust(COOKIE_SIZE, b"\0")


def check_cookie(data: bytes) -> bool:
    return data.startswith(MAGIC_MAJOR)


def _pad(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


def pack(sender: int, type_id: int, payload: bytes = b"", t_s: float | None = None,
         seq: int = 0) -> bytes:
    """One VRPN message: header, payload, padding."""
    t = time.time() if t_s is None else t_s
    sec = int(t)
    head = struct.pack(">iiiiii", HEADER_SIZE + len(payload), sec, int((t - sec) * 1e6),
                       sender, type_id, seq)
    return head + payload + b"\0" * (_pad(len(payload)) - len(payload))


def describe(kind: int, which: int, name: str) -> bytes:
    """A sender (kind -1) or type (kind -2) description: which id means which name."""
    raw = name.encode() + b"\0"
    return pack(which, kind, struct.pack(">i", len(raw)) + raw)


def unpack_messages(buf: bytearray):
    """Complete messages at the start of buf -> [(sender, type, payload, time_s)]; the
    bytes they used are removed from buf."""
    out = []
    while len(buf) >= HEADER_SIZE:
        length, sec, usec, sender, type_id = struct.unpack_from(">iiiii", buf)
        if length < HEADER_SIZE or length > 1 << 20:
            raise ValueError(f"bad VRPN message length {length}")
        total = HEADER_SIZE + _pad(length - HEADER_SIZE)
        if len(buf) < total:
            break
        out.append((sender, type_id, bytes(buf[HEADER_SIZE:length]), sec + usec * 1e-6))
        del buf[:total]
    return out


def _lob_port(data: bytes) -> int | None:
    """The TCP port of a client's UDP request "ADDRESS PORT\\0" (None: not one)."""
    try:
        words = data.split(b"\0", 1)[0].decode("ascii").split()
        port = int(words[1]) if len(words) == 2 and words[1].isdigit() else 0
    except (UnicodeDecodeError, ValueError):
        return None
    return port if 0 < port < 65536 else None


def pose_messages(result, senders: np.ndarray, t_s: float) -> np.ndarray:
    """Pos_Quat messages (POSE_MESSAGE records) of the frame's tracked bodies; `senders`
    gives our sender id of each body in result.poses order."""
    p = result.poses
    valid = np.asarray(p.valid, bool) & (senders >= 0)
    n = int(valid.sum())
    m = np.zeros(n, POSE_MESSAGE)
    sec = int(t_s)
    m["len"] = HEADER_SIZE + 64
    m["sec"], m["usec"] = sec, int((t_s - sec) * 1e6)
    m["sender"] = senders[valid]
    m["type"] = OUR_TYPES.index(POS_QUAT)
    m["pos"] = np.asarray(p.position)[valid]
    m["quat"] = np.asarray(p.quaternion)[valid]
    return m
