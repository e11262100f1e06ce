"""When a datagram reached us, as the kernel saw it, for clock-sync answers.

An echo answer carries one server time, and a client takes it as the middle of its round
trip. Stamped in Python after `recvfrom`, that time lands late by however long the thread
waited for the GIL or the CPU (up to milliseconds on a loaded machine), and the client's
offset is off by that much. The kernel's receive stamp (SO_TIMESTAMPNS) and the moment the
answer is built bracket the time the request spent with us; their midpoint is what the
client's arithmetic assumes, so the server's own delay cancels out.
"""

from __future__ import annotations

import platform
import socket
import struct
import sys
import time

_TIMESPEC = struct.Struct("@qq")  # struct timespec on 64-bit Linux: seconds, nanoseconds
# Python's socket module does not export it; 35 is asm-generic's value (x86, Arm, RISC-V)
_GENERIC_ABI = sys.platform.startswith("linux") and platform.machine() in (
    "x86_64", "aarch64", "arm64", "riscv64") and _TIMESPEC.size == 16
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35 if _GENERIC_ABI else None)
STAMPING = SO_TIMESTAMPNS is not None


def stamp_arrivals(sock: socket.socket) -> bool:
    """Ask the kernel to stamp each datagram's arrival; False where it cannot."""
    if not STAMPING:
        return False
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    except OSError:
        return False
    return True


def realtime_to_monotonic_ns(realtime_ns: int) -> int:
    """A CLOCK_REALTIME stamp (the kernel's) on the monotonic clock the daemon keeps."""
    before = time.monotonic_ns()
    now_realtime = time.time_ns()
    after = time.monotonic_ns()
    return realtime_ns - now_realtime + (before + after) // 2


def receive_stamped(sock: socket.socket, size: int = 65536):
    """`(data, addr, arrived_ns)`: arrived_ns on the monotonic clock, None when the socket
    gave no stamp (not asked for, or a system without SO_TIMESTAMPNS)."""
    if not STAMPING:
        data, addr = sock.recvfrom(size)
        return data, addr, None
    data, ancillary, _flags, addr = sock.recvmsg(size, socket.CMSG_SPACE(_TIMESPEC.size))
    for level, kind, payload in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS \
                and len(payload) >= _TIMESPEC.size:
            seconds, nanoseconds = _TIMESPEC.unpack_from(payload)
            return data, addr, realtime_to_monotonic_ns(seconds * 1_000_000_000 + nanoseconds)
    return data, addr, None


def residence_midpoint_ns(arrived_ns: int | None) -> int:
    """The middle of a request's stay with us: from the kernel's arrival stamp to now (the
    answer is about to leave). Without a stamp, now."""
    now = time.monotonic_ns()
    if arrived_ns is None or arrived_ns > now:
        return now
    return (arrived_ns + now) // 2
