"""The MAVLink link to an autopilot: a component that keeps the conversation autopilots expect.

An autopilot judges a vision source by more than its poses: it counts the sequence numbers
of each sender (a sender stuck at 0 reads as near-total packet loss), looks for the
sender's HEARTBEAT once a second, measures the clock offset with TIMESYNC (PX4 and
ArduPilot ask; a silent companion leaves their latency compensation guessing), and
ArduPilot flies without GPS only once told where the local frame is on the Earth
(SET_GPS_GLOBAL_ORIGIN). This module does that part, for one link.

Transports come from pymavlink's mavutil.mavlink_connection (a UART path; udpin:/udp:
listen and answer whoever sends, udpout: sends to, tcp: connects to HOST:PORT). The
framing is ours, MAVLink 2 from pymavlink's `common` dialect, so every message leaves
through one MAVLink object that numbers them; writes raise on failure (mavutil's own
print and swallow), so the caller notices and reopens.
"""

from __future__ import annotations

import logging
import math
import select
import threading
import time

from daemon.publish.bad_input import BadInput

log = logging.getLogger("mocapd.publish")

HEARTBEAT_PERIOD_S = 1.0
TIMESYNC_PERIOD_S = 1.0
AUTOPILOT_LOST_S = 5.0  # no heartbeat for this long: a new one is a new (rebooted) autopilot
WRITE_TIMEOUT_S = 0.2  # a UART nobody drains fails a write rather than blocking it
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
NOT_AUTOPILOTS = (6, 18, 26, 27)  # GCS, onboard controller, gimbal, ADS-B


def _enum_name(enums, table: str, value: int) -> str:
    entry = enums.get(table, {}).get(value)
    if entry is None:
        return str(value)
    prefix = table + "_"
    return entry.name.removeprefix(prefix).lower()


class MavlinkLink:
    """One connection, its HEARTBEAT, TIMESYNC and origin; poses go out through send()."""

    def __init__(self, device: str, baud: int, system_id: int, component_id: int,
                 origin: tuple[float, float, float] | None = None) -> None:
        # deferred on purpose: loads pymavlink only where used
        from pymavlink.dialects.v20 import common

        self.dialect = common
        self.device, self.baud, self.origin = device, baud, origin
        self.mav = common.MAVLink(self, srcSystem=system_id, srcComponent=component_id)
        self.parser = common.MAVLink(None)
        self.parser.robust_parsing = True
        self.conn = None
        self._kind = None
        self._lock = threading.Lock()  # one writer at a time: sequence numbers in order
        self._next_heartbeat = 0.0
        self._next_timesync = 0.0
        self._asked: dict[int, int] = {}  # our TIMESYNC ts1 -> monotonic_ns sent
        self.autopilot: dict | None = None
        self._autopilot_seen = -math.inf
        self.heartbeats_received = 0
        self.timesync_answered = 0  # the autopilot's requests we answered
        self.timesync_rtt_ms: float | None = None  # our last request's round trip
        self.timesync_offset_ns: int | None = None  # autopilot clock minus ours
        self.origin_sent = 0
        self.received = 0
        # bytes that are no MAVLink message we know (line noise, another dialect, junk):
        # counted by kind, logged once a minute each
        self.bad = BadInput(log, f"mavlink {device}")
        self.other_dialect = 0  # messages of ids outside the common dialect

    # ---- the connection ------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        return self.conn is not None

    def open(self) -> None:
        # deferred on purpose: loads pymavlink only where used
        from pymavlink import mavutil

        conn = mavutil.mavlink_connection(self.device, baud=self.baud, retries=0,
                                          source_system=self.mav.srcSystem,
                                          source_component=self.mav.srcComponent)
        if isinstance(conn, mavutil.mavserial):
            conn.port.write_timeout = WRITE_TIMEOUT_S
            self._kind = "serial"
        elif isinstance(conn, mavutil.mavtcp):
            conn.port.settimeout(WRITE_TIMEOUT_S)
            self._kind = "tcp"
        else:
            self._kind = "udp"
        self._next_heartbeat = self._next_timesync = 0.0
        self.conn = conn

    def close(self) -> None:
        conn, self.conn = self.conn, None
        if conn is not None:
            try:
                conn.close()
            except OSError:
                pass

    def write(self, buf: bytes) -> None:
        """The MAVLink object's output (it calls file.write); raises when it cannot."""
        conn = self.conn
        if conn is None:
            raise OSError("link not open")
        if self._kind == "serial":
            conn.port.write(bytes(buf))
        elif self._kind == "tcp":
            conn.port.sendall(bytes(buf))
        else:  # UDP: a datagram lost is lost (mavutil sends to the peers it has heard)
            conn.write(bytes(buf))

    def send(self, msg) -> None:
        with self._lock:
            seq = self.mav.seq
            try:
                self.mav.send(msg)
            except Exception:
                # a write that failed may have put part of the message on the wire: its
                # number is spent, so the autopilot counts a loss, never a repeat
                self.mav.seq = (seq + 1) % 256
                raise

    # ---- reading and the periodic messages -------------------------------------------------

    def poll(self, timeout_s: float) -> None:
        """Wait up to timeout_s for bytes from the autopilot and handle its messages."""
        conn = self.conn
        if conn is None:
            return
        fd = conn.port.fileno()
        if not select.select([fd], [], [], max(0.0, timeout_s))[0]:
            return
        if self._kind == "serial":
            data = conn.port.read(max(1, conn.port.in_waiting))
        elif self._kind == "tcp":
            data = conn.port.recv(4096)
            if not data:
                raise OSError("the autopilot closed the connection")
        else:
            data = conn.recv()
        self.receive(bytes(data))

    def receive(self, data: bytes) -> None:
        """Parse bytes from the autopilot and handle its messages. Junk is counted, never
        raised: a noisy UART must not make the link reopen. Only a failed write of our
        answer (OSError) goes up, to the caller that reopens the link."""
        try:
            msgs = self.parser.parse_buffer(data) or ()
        except Exception as exc:  # noqa: BLE001 - pymavlink's MAVError, struct errors...
            self.bad(f"bytes the parser refused ({type(exc).__name__})", exc)
            return
        for msg in msgs:
            kind = msg.get_type()
            if kind == "BAD_DATA":
                self.bad("bad data (CRC, length or framing)", getattr(msg, "reason", ""))
                continue
            if kind.startswith("UNKNOWN_"):  # another dialect's (ArduPilot sends many):
                self.other_dialect += 1      # normal traffic, not junk, so not logged
                continue
            try:
                self.handle(msg)
            except OSError:
                raise
            except Exception as exc:  # noqa: BLE001 - a message with values we cannot use
                self.bad(f"{kind} that failed ({type(exc).__name__})", exc)

    def handle(self, msg) -> None:
        if msg.get_srcSystem() == self.mav.srcSystem and \
                msg.get_srcComponent() == self.mav.srcComponent:
            return  # our own, echoed
        self.received += 1
        kind = msg.get_type()
        if kind == "HEARTBEAT" and msg.autopilot != MAV_AUTOPILOT_INVALID \
                and msg.type not in NOT_AUTOPILOTS:
            self._heard_autopilot(msg)
        elif kind == "TIMESYNC":
            now = time.monotonic_ns()
            if msg.tc1 == 0:  # a request: our clock, their stamp back
                self.send(self.mav.timesync_encode(now, msg.ts1))
                self.timesync_answered += 1
            elif msg.ts1 in self._asked:  # the answer to one of ours
                sent = self._asked.pop(msg.ts1)
                self.timesync_rtt_ms = (now - sent) / 1e6
                self.timesync_offset_ns = int(msg.tc1 - (sent + now) // 2)

    def _heard_autopilot(self, msg) -> None:
        now = time.monotonic()
        new = now - self._autopilot_seen > AUTOPILOT_LOST_S
        self._autopilot_seen = now
        self.heartbeats_received += 1
        enums = self.dialect.enums
        self.autopilot = {
            "system_id": msg.get_srcSystem(), "component_id": msg.get_srcComponent(),
            "autopilot": _enum_name(enums, "MAV_AUTOPILOT", msg.autopilot),
            "type": _enum_name(enums, "MAV_TYPE", msg.type),
            "state": _enum_name(enums, "MAV_STATE", msg.system_status),
            "armed": bool(msg.base_mode & 128)}
        if new and self.origin is not None:
            self.send_origin(msg.get_srcSystem())

    def send_origin(self, target_system: int) -> None:
        """SET_GPS_GLOBAL_ORIGIN and SET_HOME_POSITION at the configured origin: where the
        local frame's (0, 0, 0) is on the Earth, and home there."""
        lat, lon, alt_m = self.origin
        lat_e7, lon_e7, alt_mm = round(lat * 1e7), round(lon * 1e7), round(alt_m * 1000)
        t_us = time.monotonic_ns() // 1000
        self.send(self.mav.set_gps_global_origin_encode(target_system, lat_e7, lon_e7,
                                                         alt_mm, t_us))
        self.send(self.mav.set_home_position_encode(target_system, lat_e7, lon_e7, alt_mm,
                                                     0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0],
                                                     0.0, 0.0, 0.0, t_us))
        self.origin_sent += 1

    def tick(self) -> float:
        """Send what is due (HEARTBEAT, our TIMESYNC request); seconds until the next."""
        now = time.monotonic()
        if now >= self._next_heartbeat:
            self.send(self.mav.heartbeat_encode(MAV_TYPE_ONBOARD_CONTROLLER,
                                                MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE))
            self._next_heartbeat += HEARTBEAT_PERIOD_S  # on the beat, unless far behind
            if self._next_heartbeat <= now:
                self._next_heartbeat = now + HEARTBEAT_PERIOD_S
        if now >= self._next_timesync and self.autopilot is not None:
            stamp = time.monotonic_ns()
            self._asked = {k: v for k, v in self._asked.items() if stamp - v < 5e9}
            self._asked[stamp] = stamp
            self.send(self.mav.timesync_encode(0, stamp))
            self._next_timesync = now + TIMESYNC_PERIOD_S
        due = self._next_heartbeat if self.autopilot is None else min(self._next_heartbeat,
                                                                        self._next_timesync)
        return max(0.0, due - time.monotonic())

    def status(self) -> dict:
        ap = None
        if self.autopilot is not None:
            ap = dict(self.autopilot, heartbeats=self.heartbeats_received,
                      age_s=round(time.monotonic() - self._autopilot_seen, 3))
        return {"autopilot": ap, "messages_sent": self.mav.total_packets_sent,
                "messages_received": self.received,
                "timesync_answered": self.timesync_answered,
                "timesync_rtt_ms": self.timesync_rtt_ms, "origin_sent": self.origin_sent,
                "bad_input": dict(self.bad.counts), "other_dialect": self.other_dialect}
