"""Echo answers stamped from the kernel's arrival time, not from when Python got round to
the datagram: a server thread that is late does not bias a client's clock offset."""

import socket
import struct
import time

import pytest

from daemon.publish import arrival_stamps as stamps
from daemon.publish import natnet_wire as nn


def _pair():
    server = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    server.bind(("127.0.0.1", 0))
    server.settimeout(2.0)
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    return server, client


def _warm(server, client) -> None:
    """The kernel turns receive stamping on for the whole system a moment after the first
    socket asks (a deferred switch); until then a datagram is stamped when it is read. A
    server asks at start, long before its first client: so does this, then waits that out."""
    for _ in range(50):
        client.sendto(b"warm", server.getsockname())
        time.sleep(0.02)
        _data, _addr, arrived = stamps.receive_stamped(server)
        if arrived is not None and time.monotonic_ns() - arrived >= 15_000_000:
            return


@pytest.mark.skipif(not stamps.STAMPING, reason="kernel receive stamps: Linux on x86/Arm/RISC-V")
def test_arrival_is_the_kernels_time_not_the_readers():
    server, client = _pair()
    try:
        assert stamps.stamp_arrivals(server)
        _warm(server, client)
        sent = time.monotonic_ns()
        client.sendto(b"ping", server.getsockname())
        time.sleep(0.08)  # the reader is late by 80 ms
        data, _addr, arrived = stamps.receive_stamped(server)
        read = time.monotonic_ns()
        assert data == b"ping"
        assert arrived is not None
        assert sent - 1_000_000 <= arrived <= sent + 20_000_000  # at the send, not the read
        assert read - arrived >= 60_000_000
    finally:
        server.close()
        client.close()


def test_unstamped_socket_gives_no_arrival_and_now_as_the_midpoint():
    server, client = _pair()
    try:
        client.sendto(b"ping", server.getsockname())
        _data, _addr, arrived = stamps.receive_stamped(server)
        assert arrived is None
        before = time.monotonic_ns()
        assert before <= stamps.residence_midpoint_ns(None) <= time.monotonic_ns()
    finally:
        server.close()
        client.close()


@pytest.mark.skipif(not stamps.STAMPING, reason="kernel receive stamps: Linux on x86/Arm/RISC-V")
def test_late_server_thread_leaves_the_echo_offset_unbiased():
    """The request waits 60 ms before the server reads it and answers at once: stamped on
    reading, the client's offset would be +30 ms; stamped from the kernel's arrival, the
    server's stay is split evenly and the offset stays within a few ms of the truth (0:
    one clock)."""
    server, client = _pair()
    try:
        stamps.stamp_arrivals(server)
        _warm(server, client)
        sent = time.monotonic_ns()
        client.sendto(struct.pack("<HHQ", nn.NAT_ECHOREQUEST, 8, sent), server.getsockname())
        time.sleep(0.06)
        data, addr, arrived = stamps.receive_stamped(server)
        server.sendto(nn.echo_response(data, stamps.residence_midpoint_ns(arrived)), addr)
        client.settimeout(2.0)
        reply = client.recv(64)
        back = time.monotonic_ns()
        _msg, _size, stamp, server_ns = struct.unpack("<HHQQ", reply)
        assert stamp == sent
        offset_ms = (server_ns - (sent + back) / 2) / 1e6
        assert abs(offset_ms) < 5.0
    finally:
        server.close()
        client.close()
