"""systemd's notify protocol, with no library: one datagram per message to $NOTIFY_SOCKET.

READY=1 once the rig and cameras are up, WATCHDOG=1 from the frame loop (so a hung loop is
restarted, not a hung thread elsewhere), STATUS= with rate and latency, RELOADING=1 around
a reload, STOPPING=1 on the way out.
"""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger("mocapd")


def sd_notify(message: str) -> bool:
    """Send one notify message; False when not under systemd (no NOTIFY_SOCKET), or when
    the socket would block: the frame loop sends its status every second and must never
    wait for a manager that stopped reading."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
            s.connect(address)
            s.send(message.encode(), socket.MSG_DONTWAIT)
        return True
    except OSError as exc:
        log.debug("sd_notify failed: %s", exc)
        return False


def watchdog_interval_s() -> float | None:
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    return int(usec) / 2e6
