"""mocapd.toml's output tables ([[udp]], [[serial]], [[mavlink]], [natnet], [[vrpn]]): what each
holds, read and checked with the other tables' errors (one line naming the file and key).

Apart from daemon.config.mocapd (which reads the whole file and calls these) because the
outputs are half of the file's keys, and `mocapd start`'s --udp/--serial/--mavlink/--natnet/
--vrpn options build the same records from the command line (parse_address, parse_serial,
mavlink_device).
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, fields
from pathlib import Path

from daemon.config.check import _bool, _check_keys, _number, _string
from daemon.publish.mavlink import MESSAGES, WORLD_TO_NED
from daemon.publish.natnet_commands import networks


@dataclass(frozen=True)
class UdpOut:
    host: str
    port: int
    rate_hz: float = 0.0
    ttl: int = 1
    bodies: tuple[int, ...] | None = None
    interface: str | None = None  # local address multicast leaves from
    markers: bool = True  # the labelled markers section, when a marker set is configured


@dataclass(frozen=True)
class SerialOut:
    device: str
    baud: int = 115200
    rate_hz: float | None = None  # None: "auto", the highest rate the line carries (<= 100)
    bodies: tuple[int, ...] | None = None


@dataclass(frozen=True)
class MavlinkOut:
    device: str  # a UART, or mavutil's udpin:/udpout:/udp:/tcp:HOST:PORT
    body: int
    baud: int = 921600
    message: str = "vision_position_estimate"
    frame: str = "enu"
    rate_hz: float | None = None  # None: "auto", 50 Hz or what a UART carries
    system_id: int = 1
    component_id: int = 197
    origin: tuple[float, float, float] | None = None  # lat deg, lon deg, alt m (MSL)


@dataclass(frozen=True)
class NatnetOut:
    # local address: command port, multicast interface; loopback unless one is given, so a
    # server is on a network only on purpose
    interface: str = "127.0.0.1"
    command_port: int = 1510
    data_port: int = 1511
    multicast: bool = True
    group: str = "239.255.42.99"
    up_axis: str = "z"
    ttl: int = 1
    rate_hz: float = 0.0
    legacy_unlabeled: bool = False
    marker_sets: bool = True
    markerset_id: int = 65535  # model id of the live marker set's labelled markers
    record_dir: Path | None = None  # where StartRecording records (None: it answers -1)
    # who may send the recording commands (addresses or networks): they write to the disk
    record_from: tuple[str, ...] = ("127.0.0.1",)
    record_max_s: float = 3600.0  # a take StartRecording began stops after this (0: never)
    record_max_mb: float = 2000.0  # ... or at this size, whichever first (0: no limit)


@dataclass(frozen=True)
class VrpnOut:
    host: str = "127.0.0.1"  # a bare port serves this computer only; give an address to expose
    port: int = 3883
    rate_hz: float = 0.0
    udp: bool = True


def parse_address(text: str, what: str = "address") -> tuple[str, int]:
    """'HOST:PORT' -> (host, port); ValueError with the reason."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"expected HOST:PORT with a port 1-65535, got {text!r}")
    return host, int(port)


def parse_serial(text: str, default_baud: int = 115200) -> tuple[str, int]:
    """'DEV[:BAUD]' -> (device, baud); pyserial URLs (socket://, loop://) and mavutil's
    network addresses (udpin:HOST:PORT, udpout:..., tcp:...) are kept whole."""
    text = str(text)
    if "://" not in text and not text.startswith(("udp:", "udpin:", "udpout:", "tcp:")):
        dev, sep, baud = text.rpartition(":")
        if sep and baud.isdigit() and dev:
            return dev, int(baud)
    return text, default_baud


def _ids(w, table, key, prefix):
    if key not in table:
        return None
    v = table[key]
    if not isinstance(v, list) or not all(isinstance(i, int) and not isinstance(i, bool)
                                          for i in v):
        w.fail(prefix + key, f"expected a list of body ids, got {v!r}")
    return tuple(v)


def _udp(w, t, p) -> UdpOut:
    _check_keys(w, t, {"address", "rate_hz", "ttl", "bodies", "interface", "markers"}, p)
    try:
        host, port = parse_address(_string(w, t, "address", p))
    except ValueError as exc:
        w.fail(p + "address", str(exc))
    interface = t.get("interface")
    if interface is not None:
        try:
            if not isinstance(interface, str):
                raise ValueError
            ipaddress.IPv4Address(interface)
        except ValueError:
            w.fail(p + "interface", f"expected a local IPv4 address, got {interface!r}")
    return UdpOut(host, port, _number(w, t, "rate_hz", p, 0.0, lo=0),
                  _number(w, t, "ttl", p, 1, int, 0, 255), _ids(w, t, "bodies", p), interface,
                  _bool(w, t, "markers", p, True))


def _rate(w, t, p):
    """rate_hz: "auto" (None: fitted to the line when the outputs are made) or Hz >= 0."""
    if t.get("rate_hz") == "auto":
        return None
    if isinstance(t.get("rate_hz"), str):
        w.fail(p + "rate_hz", f'expected "auto" or a rate in Hz, got {t["rate_hz"]!r}')
    return _number(w, t, "rate_hz", p, None, lo=0)


def _serial(w, t, p) -> SerialOut:
    _check_keys(w, t, {"device", "baud", "rate_hz", "bodies"}, p)
    return SerialOut(_string(w, t, "device", p), _number(w, t, "baud", p, 115200, int, 50),
                     _rate(w, t, p), _ids(w, t, "bodies", p))


def _mavlink(w, t, p) -> MavlinkOut:
    _check_keys(w, t, {"device", "baud", "body", "message", "frame", "rate_hz", "system_id",
                       "component_id", "origin"}, p)
    if "body" not in t:
        w.fail(p + "body", "missing (the id of the rigid body to send)")
    device = _string(w, t, "device", p)
    try:
        mavlink_device(device)
    except ValueError as exc:
        w.fail(p + "device", str(exc))
    origin = None
    if "origin" in t:
        o = t["origin"]
        if not (isinstance(o, list) and len(o) == 3 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in o)
                and -90 <= o[0] <= 90 and -180 <= o[1] <= 180 and -1000 <= o[2] <= 10000):
            w.fail(p + "origin", "expected [latitude_deg, longitude_deg, altitude_m] "
                                 f"(-90..90, -180..180, -1000..10000), got {o!r}")
        origin = tuple(float(v) for v in o)
    return MavlinkOut(device, _number(w, t, "body", p, 0, int, 0, 65535),
                      _number(w, t, "baud", p, 921600, int, 50),
                      _string(w, t, "message", p, "vision_position_estimate", MESSAGES),
                      _string(w, t, "frame", p, "enu", tuple(WORLD_TO_NED)),
                      _rate(w, t, p),
                      _number(w, t, "system_id", p, 1, int, 1, 255),
                      _number(w, t, "component_id", p, 197, int, 0, 255), origin)


def mavlink_device(text: str) -> str:
    """A [[mavlink]] device as mavutil opens it: a UART path, or udpin:/udp: (listen),
    udpout: (send to), tcp: (connect to) with HOST:PORT; ValueError with the reason."""
    scheme, sep, rest = text.partition(":")
    if not sep or scheme not in ("udp", "udpin", "udpout", "tcp"):
        if text.startswith(("tcpin:", "udpbcast:", "mcast:", "ws:", "wss:", "wsserver:")):
            raise ValueError(f"{scheme}: is not supported; use a UART path, udpin:, udpout: "
                             "or tcp: with HOST:PORT")
        return text  # a UART path
    try:
        parse_address(rest)
    except ValueError as exc:
        raise ValueError(f"{scheme}: {exc}") from None
    return text


def _natnet(w, t, p, base: Path | None = None) -> NatnetOut:
    d = NatnetOut()
    _check_keys(w, t, {f.name for f in fields(NatnetOut)}, p)
    group = _string(w, t, "group", p, d.group)
    if not _ipv4(group) or not ipaddress.ip_address(group).is_multicast:
        w.fail(p + "group", f"expected an IPv4 multicast address (224.0.0.0/4), got {group!r}")
    if not _ipv4(_string(w, t, "interface", p, d.interface)):
        w.fail(p + "interface", f"expected the IPv4 address of a local interface (or "
                                f"0.0.0.0), got {t['interface']!r}")
    return NatnetOut(_string(w, t, "interface", p, d.interface),
                     _number(w, t, "command_port", p, d.command_port, int, 1, 65535),
                     _number(w, t, "data_port", p, d.data_port, int, 1, 65535),
                     _bool(w, t, "multicast", p, d.multicast), group,
                     _string(w, t, "up_axis", p, d.up_axis, ("z", "y")),
                     _number(w, t, "ttl", p, d.ttl, int, 0, 255),
                     _number(w, t, "rate_hz", p, d.rate_hz, lo=0),
                     _bool(w, t, "legacy_unlabeled", p, d.legacy_unlabeled),
                     _bool(w, t, "marker_sets", p, d.marker_sets),
                     _number(w, t, "markerset_id", p, d.markerset_id, int, 1, 65535),
                     (base or Path.cwd()) / _string(w, t, "record_dir", p)
                     if "record_dir" in t else None,
                     _record_from(w, t, p, d.record_from),
                     _number(w, t, "record_max_s", p, d.record_max_s, lo=0, hi=1e7),
                     _number(w, t, "record_max_mb", p, d.record_max_mb, lo=0, hi=1e9))


def _record_from(w, t, p, default) -> tuple[str, ...]:
    v = t.get("record_from", list(default))
    if not isinstance(v, list) or not all(isinstance(a, str) for a in v):
        w.fail(p + "record_from", f"expected a list of addresses, got {v!r}")
    try:
        networks(v)
    except ValueError as exc:
        w.fail(p + "record_from", f"expected IP addresses or networks (\"10.0.0.0/24\"): {exc}")
    return tuple(v)


def _ipv4(text: str) -> bool:
    try:
        return ipaddress.ip_address(text).version == 4
    except ValueError:
        return False


def _vrpn(w, t, p) -> VrpnOut:
    _check_keys(w, t, {"address", "rate_hz", "udp"}, p)
    host, port = VrpnOut.host, VrpnOut.port
    if "address" in t:
        try:
            host, port = parse_address(_string(w, t, "address", p))
        except ValueError as exc:
            w.fail(p + "address", str(exc))
    return VrpnOut(host, port, _number(w, t, "rate_hz", p, 0.0, lo=0),
                   _bool(w, t, "udp", p, True))
